import sys

from caviar_plugins.tools.scene.cli import main

sys.exit(main())
