"""The defaults the package's parts share, in one light module (the command lines' --help reads
them without loading any method)."""

# The LRF method `compute_frames`, `register`, lrf-frames and lrf-register use when none is
# given: the most repeatable shipped one ("lrf_net" is the paper's LRF-Net).
DEFAULT_METHOD = "lrf_net_plus"
# The support radius of the frames and descriptors, in mesh resolutions, where a caller gives
# none (`register`, the command lines, the experiments): the paper's.
RADIUS_MR = 15.0
# What `weights=` names besides a parameter file's path: the kind of data a shipped file was
# trained on ("objects": each learned method's own file; `lrf_jax.frames.weights.weights_file`).
WEIGHTS_KINDS = ("objects", "rooms", "streets")
