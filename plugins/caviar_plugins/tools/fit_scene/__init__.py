"""``caviar-core fit-scene``: a scene's radio materials learned from measurements
(:mod:`caviar_plugins.tools.fit_scene.cli`), and its figure
(:mod:`caviar_plugins.tools.fit_scene.report`)."""
