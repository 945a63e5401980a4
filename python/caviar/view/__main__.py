import sys

from caviar.view.cli import main

sys.exit(main())
