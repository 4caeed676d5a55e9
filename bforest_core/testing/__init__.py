from ._base import *  # noqa: F401,F403
from ._base import __all__, __doc__  # noqa: F401
