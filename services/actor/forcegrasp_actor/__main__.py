from forcegrasp_actor.actor import main

raise SystemExit(main())
