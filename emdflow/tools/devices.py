"""``emdflow devices``: which OpenCL devices can run the engine, and which one it takes.

For bringing up a board (a vendor ICD beside PoCL, two PoCLs side by side): every device
that :func:`emdflow.opencl_devices` lists is tried for real — the kernels built for a small
frame and one frame run — and the line says whether it works and, if not, the first line
of the reason (the compiler's ``error:`` line where there is one). The device the engine
takes when left to choose (``EMDFLOW_OPENCL_DEVICE``, else the first that works) is marked.
Exit code 0 when the engine can run, 1 when no device works or the chosen one does not.
``deploy/install.sh`` and ``.ci/run`` use it to decide whether to add Debian's PoCL.
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["DeviceCheck", "check_devices", "add_arguments", "run"]

#: The probe's frame: small (a build per frame size; this one is quick), but larger than
#: the receptors' reach, so every kernel runs.
PROBE_SIZE = (64, 48)


@dataclasses.dataclass(frozen=True)
class DeviceCheck:
    """One device's result: ``error`` is None when the engine ran there."""

    index: int
    name: str
    error: str | None

    @property
    def works(self) -> bool:
        return self.error is None

    def reason(self) -> str:
        """The line that says why it failed (the compiler's ``error:`` line if any)."""
        from emdflow.opencl_backend import first_error_line

        return first_error_line(self.error or "")


def _failure(exc: BaseException) -> str:
    return str(exc) or type(exc).__name__


def _run_once(model_options: dict, device) -> str:
    """The device the engine ran on, after building its kernels and running one frame."""
    from emdflow import FlowEstimator

    width, height = PROBE_SIZE
    est = FlowEstimator(width, height, device=device, **model_options)
    est.update(np.zeros((height, width), np.uint8))
    return est.device


def check_devices(model_options: dict | None = None) -> tuple[list[DeviceCheck], DeviceCheck | str]:
    """Try every listed device; returns the checks and the automatic choice: the check of
    the device the engine takes when left to choose, or the error that choice ends in.

    Raises RuntimeError (with install instructions) when there is no OpenCL platform."""
    from emdflow import opencl_devices

    options = dict(model_options or {})
    checks = []
    for index, name in opencl_devices():
        try:
            _run_once(options, index)
            error = None
        except Exception as exc:  # noqa: BLE001 - a build error, or a driver failing at run time
            error = _failure(exc)
        checks.append(DeviceCheck(index, name, error))
    try:
        chosen_name = _run_once(options, None)
    except Exception as exc:  # noqa: BLE001 - (pyopencl's errors are not RuntimeErrors)
        return checks, _failure(exc)
    chosen = next((c for c in checks if c.name == chosen_name and c.works), None)
    return checks, chosen if chosen is not None else DeviceCheck(-1, chosen_name, None)


def add_arguments(p) -> None:
    from emdflow.params import MODELS

    p.add_argument("--model", default="paper", choices=tuple(MODELS),
                   help="detector model whose kernels are built (default: %(default)s; the "
                        "daemon runs 'extended')")


def run(args) -> int:
    import os

    from emdflow.params import MODELS
    from emdflow.tools import ToolError

    try:
        checks, chosen = check_devices(MODELS[args.model])
    except RuntimeError as exc:  # no platform at all: the message says how to get one
        raise ToolError(str(exc), 1) from None
    for check in checks:
        mark = "*" if isinstance(chosen, DeviceCheck) and check.index == chosen.index else " "
        state = "works" if check.works else f"fails: {check.reason()}"
        print(f"{mark} {check.index}  {check.name}  {state}")
    how = (f"EMDFLOW_OPENCL_DEVICE={os.environ['EMDFLOW_OPENCL_DEVICE']!r}"
           if os.environ.get("EMDFLOW_OPENCL_DEVICE") else "the first device that works")
    if isinstance(chosen, DeviceCheck):
        print(f"the engine runs on {chosen.name} (*: {how}; choose another with "
              "EMDFLOW_OPENCL_DEVICE=<index or name part>)")
        return 0
    from emdflow.opencl_backend import error_summary

    raise ToolError(f"the engine cannot run ({how}): {error_summary(chosen)}", 1)
