"""Suite-wide pytest hooks."""


def pytest_collection_modifyitems(items):
    """Run the tests marked slow first (stable order otherwise): on `-n 2` the workers then share the
    short tests at the end, instead of one worker running the last long end-to-end test alone."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)
