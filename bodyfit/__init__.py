"""bodyfit: parametric human bodies with an OpenSim-exact biomechanical skeleton inside.

Layers (dependencies point one way): ``api -> service -> models``; ``clients`` talk to the wire only.
Nothing heavy is imported here.
"""

__version__ = "0.1.0"
