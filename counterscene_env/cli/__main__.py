"""``python -m counterscene_env.cli``: the ``counterscene`` command."""

import sys

from counterscene_env.cli import main

sys.exit(main())
