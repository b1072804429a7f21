"""``python -m sync4d.evaluate <name> [options]``: runs ``sync4d_tools.evaluate.<name>.main(options)``."""

import sys

from sync4d_tools.evaluate.__main__ import main

if __name__ == "__main__":
    sys.exit(main())
