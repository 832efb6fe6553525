from forcegrasp.services.actor.actor import main

raise SystemExit(main())
