import sys

from dispgns.cli import main

sys.exit(main())
