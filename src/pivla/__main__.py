import sys

from pivla.cli import main

sys.exit(main())
