"""The surrogate's size limits, once: ``elastreg train --hidden``/``--members``, a scene's
``[training] members`` and :class:`~service.surrogate.train.TrainConfig` refuse values past them
when they are read, before any data; past them a build failed on allocation (a traceback after
the data, or gigabytes taken first).

Each is far above any network worth training here (the defaults: two layers of 512, one member;
the paper's liver: three members).
"""

#: widest hidden layer: 32 x the default; two such layers are 1 GiB of float32 weights, 4 with Adam's state
MAX_WIDTH = 16384
#: most hidden layers: 32 x the default's two
MAX_LAYERS = 64
#: largest ensemble: each member is a whole network trained on its own, so the build's time grows with them
MAX_MEMBERS = 64
