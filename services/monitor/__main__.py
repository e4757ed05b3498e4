from .monitor import main

raise SystemExit(main())
