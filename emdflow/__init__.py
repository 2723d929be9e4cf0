"""emdflow — insect-vision optical flow (Quelin, Bouzerdoum & Phung 2010) on OpenCL.

Public API::

    import emdflow
    est = emdflow.FlowEstimator(width, height, backend="opencl")  # or "numpy"
    field = est.update(frame)       # 2-D uint8 (height, width) -> FlowField
    field.u, field.v                # float32 px/frame, u right, v down, NaN = undetected
    est.reset()
    s = emdflow.summarize(field)    # s.flow_x, s.flow_y px/frame (image axes), s.quality 0..255
"""

from .estimator import FlowEstimator
from .field import FlowField
from .params import EngineParams
from .summary import FlowSummary, SummaryOptions, summarize

__version__ = "0.1.0"

__all__ = [
    "FlowEstimator",
    "FlowField",
    "FlowSummary",
    "SummaryOptions",
    "EngineParams",
    "summarize",
    "opencl_devices",
    "__version__",
]


def opencl_devices():
    """List the OpenCL devices as ``[(index, "platform: device"), ...]``.

    A listed device may still be unable to build the kernels (a PoCL whose compiler does
    not know the processor): the automatic choice passes over those, and
    :attr:`FlowEstimator.device` names the device an estimator runs on.

    Raises RuntimeError (with install instructions) when pyopencl or an OpenCL platform
    is missing.
    """
    from .opencl_backend import list_devices

    return list_devices()
