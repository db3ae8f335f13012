"""The channels (topics) of a run in Foxglove's schemas: what `export --foxglove` writes, the live
stream sends and the layout's panels read."""

POSE = "/lidarloc/pose"
TRUTH = "/lidarloc/truth"
TF = "/tf"
PARTICLES = "/lidarloc/particles"
PARTICLE_CLOUD = "/lidarloc/particle_cloud"
SCAN = "/lidarloc/scan"
MAP = "/lidarloc/map"
SCENE = "/lidarloc/scene"
LOG = "/lidarloc/log"
FIGURES = "/lidarloc/figures"
