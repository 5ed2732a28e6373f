import sys

from guiding.cli import main

sys.exit(main())
