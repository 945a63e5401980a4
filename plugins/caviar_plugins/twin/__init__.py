"""The self-calibrating twin: measurements of the radio environment as data
(:mod:`~caviar_plugins.twin.measurements`), a scene's radio materials learned from them by
differentiable ray tracing (:mod:`~caviar_plugins.twin.fit`), and the modules that do it
while a run goes (:mod:`~caviar_plugins.twin.plugin`: ``scene-fitter``, and
``measurement-emulator``, a stand-in for a vehicle's measurements)."""
