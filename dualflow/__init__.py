"""DualFlow: reactive and interactive two-person motion generation (rectified flow).

This package's ``__init__`` stays light: ``import dualflow.motion`` (the numpy-only
human-motion contract that every other package reads) must never import torch.
The torch model lives in submodules imported explicitly.
"""

from dualflow.errors import DualFlowError

__all__ = ["DualFlowError"]
