"""flexmbs: planar flexible multibody simulation and structural optimization."""
from flexmbs import _core

__all__ = ["_core"]
__version__ = "0.1.0"
