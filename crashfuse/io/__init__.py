"""Reading and writing crash data: campaign folders, NHTSA EV5 tests, ISO-MME tests."""
