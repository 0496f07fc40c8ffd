import sys

from gradsep.cli import main

sys.exit(main())
