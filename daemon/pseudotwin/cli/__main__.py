"""``python -m pseudotwin.cli`` is the ``pseudotwin`` command."""

import sys

from pseudotwin.cli import main

sys.exit(main())
