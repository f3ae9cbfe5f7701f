"""M3T / SGSA platform library. Importing it applies ``M3T_REPRODUCIBLE`` (:mod:`m3t.arithmetic`) first."""
from m3t.arithmetic import pin as _pin

_pin()
