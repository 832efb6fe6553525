from forcegrasp_evaluator.evaluator import main

raise SystemExit(main())
