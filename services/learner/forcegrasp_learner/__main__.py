from forcegrasp_learner.learner import main

raise SystemExit(main())
