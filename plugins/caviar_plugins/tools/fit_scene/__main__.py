"""``python -m caviar_plugins.tools.fit_scene``: the same as ``caviar-core fit-scene``."""

import sys

from caviar_plugins.tools.fit_scene.cli import main

sys.exit(main())
