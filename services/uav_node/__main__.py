from .node import main

raise SystemExit(main())
