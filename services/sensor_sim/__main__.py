from .sim import main

raise SystemExit(main())
