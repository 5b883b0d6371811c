"""Choice of compute devices: torch device and Mitsuba variant, chosen once, overridable."""

from __future__ import annotations

import torch

from shells.errors import InputError


def torch_device(name: str | None = None) -> torch.device:
    """``cuda`` when available unless ``name`` says otherwise."""
    if name is None:
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name not in ("cpu", "cuda"):
        raise InputError(f"--device {name}: expected 'cpu' or 'cuda'")
    if name == "cuda" and not torch.cuda.is_available():
        raise InputError("--device cuda: no CUDA device is visible to torch; use --device cpu")
    return torch.device(name)


def mitsuba_variant(name: str | None = None) -> str:
    """Set and return the Mitsuba variant: cuda_ad_rgb on a GPU, llvm_ad_rgb otherwise."""
    import mitsuba as mi

    if name is None:
        name = "cuda_ad_rgb" if torch.cuda.is_available() else "llvm_ad_rgb"
    if name not in mi.variants():
        raise InputError(f"Mitsuba variant '{name}' is not available; choose from {mi.variants()}")
    if mi.variant() != name:
        mi.set_variant(name)
    return name
