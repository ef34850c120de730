import sys

from uvatar.cli.main import main

sys.exit(main())
