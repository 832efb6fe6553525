from forcegrasp.services.evaluator.evaluator import main

raise SystemExit(main())
