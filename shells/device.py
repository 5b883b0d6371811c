"""Choice of compute devices: torch device and Mitsuba variant, chosen once, overridable."""

from __future__ import annotations

import functools

import torch

from shells.errors import InputError
from shells.files import uninterrupted


def torch_device(name: str | None = None) -> torch.device:
    """``cuda`` when available unless ``name`` says otherwise."""
    if name is None:
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name not in ("cpu", "cuda"):
        raise InputError(f"--device {name}: expected 'cpu' or 'cuda'")
    if name == "cuda" and not torch.cuda.is_available():
        raise InputError("--device cuda: no CUDA device is visible to torch; use --device cpu")
    return torch.device(name)


def mitsuba_variant(name: str | None = None, device: torch.device | str | None = None) -> str:
    """Set and return the Mitsuba variant.

    ``name`` (a config's ``render.variant``) wins; otherwise it follows the torch ``device``
    the Dr.Jit arrays are shared with (cuda_ad_rgb for CUDA, llvm_ad_rgb for the CPU), and
    without a device it is cuda_ad_rgb when CUDA is available. A variant on another device
    than ``device`` is an error: torch and Dr.Jit exchange arrays without copies.
    """
    import mitsuba as mi

    kind = None if device is None else torch.device(device).type
    if name is None:
        cuda = torch.cuda.is_available() if kind is None else kind == "cuda"
        name = "cuda_ad_rgb" if cuda else "llvm_ad_rgb"
    elif kind is not None and name.startswith("cuda") != (kind == "cuda"):
        raise InputError(f"render.variant '{name}' does not run on the torch device '{kind}'; "
                         f"set render.variant to null (chosen from the device) or match them")
    if name not in mi.variants():
        raise InputError(f"Mitsuba variant '{name}' is not available; choose from {mi.variants()}")
    if mi.variant() != name:
        # setting a variant imports Mitsuba's Python plugins; a Ctrl-C in the middle of that
        # import leaves a SystemError and a traceback, so it waits until the import is done
        with uninterrupted():
            mi.set_variant(name)
    return name


@functools.cache
def drjit_llvm() -> bool:
    """Whether Dr.Jit's LLVM backend (the CPU kernels) is usable here: it needs libLLVM at run
    time."""
    import drjit as dr

    return bool(dr.has_backend(dr.JitBackend.LLVM))
