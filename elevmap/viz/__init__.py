"""Visualisation: rerun recordings (:mod:`.log`) and matplotlib figures (:mod:`.plots`).

Every ``rerun`` call that writes a recording lives in this package; the maths never imports it.
"""

from .log import *  # noqa: F401,F403
from .log import __all__
