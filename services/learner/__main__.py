from forcegrasp.services.learner.learner import main

raise SystemExit(main())
