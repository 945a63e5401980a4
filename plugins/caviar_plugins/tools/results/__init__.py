"""The result tables of docs/results (``python -m caviar_plugins.tools.results.X``;
``scripts/sar-results.sh`` runs them all).

* :mod:`~caviar_plugins.tools.results.sar`: the SAR mission table (random, tree and oracle
  beam selection);
* :mod:`~caviar_plugins.tools.results.degradation`: the image-degradation table (packet loss
  against PSNR);
* :mod:`~caviar_plugins.tools.results.physical`: the physical-protocol result set, from the
  measured results.
"""
