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


#: the physics layout's input: POD modes of the linear response its network reads (--features)
#: and Adam's L2 weight decay on its weight matrices, not its biases or PReLU slopes
#: (--weight-decay; train.decay_groups). Chosen for whole-surface builds, the default region, on
#: eighteen calibration sites: 64 and 1e-4 generalise better to sites a build kept every load off
#: (a scene's keep_off) and lost 4.2 % there (docs/performance.md, sessions 32 and 33)
FEATURES = 256
WEIGHT_DECAY = 0.0
#: largest weight decay: past 1 the weights are held at zero, whatever the data
MAX_WEIGHT_DECAY = 1.0
