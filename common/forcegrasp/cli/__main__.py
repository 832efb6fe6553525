from forcegrasp.cli import main

raise SystemExit(main())
