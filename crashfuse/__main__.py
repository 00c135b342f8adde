from crashfuse.cli import main

raise SystemExit(main())
