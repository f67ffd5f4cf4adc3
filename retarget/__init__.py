"""Human-to-robot retargeting with CasADi (no torch import here).

The robot trajectory type lives in :mod:`retarget.trajectory`; the solvers in
their own modules, imported explicitly.
"""

from retarget.errors import RetargetError
from retarget.trajectory import RobotTrajectory

__all__ = ["RetargetError", "RobotTrajectory"]
