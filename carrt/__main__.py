import sys

from carrt.cli import main

sys.exit(main())
