import sys

from caviar_plugins.osm.cli import main

sys.exit(main())
