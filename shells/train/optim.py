"""The stages' optimiser: torch's fused Adam, the hash tables' gradients kept in persistent
sinks on the CPU.

A step touches a small share of a large hash table (lego at 800x800: about a tenth of its 13 M
rows). Through autograd, every lookup's backward zeroes a table-sized gradient, scatters into
it and hands it over, which at 800x800 cost more than the scatter itself; with `GridAdam` the
compiled backward (`shells.fields.hashgrid_cpu`) adds into one buffer per grid that lives as
long as the optimiser and is zeroed after the step. The update is Adam's over the whole
table as before (a lazy Adam that moves only the touched rows measured slower here: at a
tenth of the rows its reads hit nearly every cache line of the table anyway, in a less regular
order; docs/notes). The state is torch's Adam state, so checkpoints load either way.
"""

from __future__ import annotations

from typing import Any

import torch

from shells.device import drjit_llvm
from shells.fields.hashgrid import HashGrid


def sink_possible(field: torch.nn.Module) -> bool:
    """Gradient sinks apply: the tables are float32 CPU tensors on the compiled path (which
    needs Dr.Jit's LLVM backend for its forward), and one process trains (a gradient sink is
    not all-reduced)."""
    import torch.distributed as tdist

    grids = [m for m in field.modules() if isinstance(m, HashGrid)]
    return (bool(grids) and drjit_llvm()
            and all(g.params.device.type == "cpu" and g.params.dtype == torch.float32
                    for g in grids)
            and not (tdist.is_available() and tdist.is_initialized()
                     and tdist.get_world_size() > 1))


class GridAdam(torch.optim.Adam):
    """torch's fused Adam over every parameter, the hash tables' gradients taken from the
    grids' persistent sinks: the compiled backward adds into the sink (no table-sized gradient
    is allocated, zeroed and handed to autograd for each lookup), the step reads it as the
    table's ``.grad`` and zeroes it after. The same update as
    `torch.optim.Adam` with the gradients autograd would have given."""

    def __init__(self, groups: list[dict[str, Any]], grids: list[HashGrid], **kw: Any) -> None:
        super().__init__(groups, **kw)
        self._grids = list(grids)
        for g in grids:
            g.use_gradient_sink(True)

    def zero_grad(self, set_to_none: bool = True) -> None:
        super().zero_grad(set_to_none=set_to_none)
        for g in self._grids:  # a gradient a step left without an update
            self._clear(g)

    @staticmethod
    def _clear(g: HashGrid) -> None:
        if g.sink_dirty:  # a memset: faster here than zeroing the touched rows alone
            g.grad_sink.zero_()
            g.sink_dirty = False

    @torch.no_grad()
    def step(self, closure=None):  # type: ignore[override]
        for g in self._grids:
            if g.sink_dirty:
                g.params.grad = g.grad_sink.view(-1)
        try:
            return super().step(closure)
        finally:
            for g in self._grids:
                if g.sink_dirty:
                    g.params.grad = None
                    self._clear(g)


def use_hashgrid(field: torch.nn.Module, path: str) -> None:
    """``train.hashgrid`` / ``finetune.hashgrid``: "compiled" or "torch" lookups with gradient
    for every hash grid of ``field`` (`HashGrid.training_path`)."""
    for m in field.modules():
        if isinstance(m, HashGrid):
            m.training_path = "auto" if path == "compiled" else "torch"


def make_optimizer(field: torch.nn.Module, lr_grid: float, lr_mlp: float,
                   sink: bool | None = None) -> torch.optim.Adam:
    """Adam with two groups: hash tables (high lr, as Instant-NGP) and MLP weights.

    torch's fused Adam (one pass over each tensor: on the CPU a small fraction of the
    per-tensor Adam's time a step; the same update to float32 rounding,
    tests/test_training.py), as `GridAdam` (the tables' gradients from the grids' sinks)
    where `sink_possible`. ``sink`` True/False forces the choice (True where it is not
    possible is an error)."""
    grids = [m for m in field.modules() if isinstance(m, HashGrid)]
    grid_ids = {id(p) for g in grids for p in g.parameters()}
    tables = [p for p in field.parameters() if id(p) in grid_ids]
    mlp = [p for p in field.parameters() if id(p) not in grid_ids]
    possible = sink_possible(field) and all(
        g.training_path == "auto" for g in grids)  # the torch path gives autograd gradients
    if sink and not possible:
        raise ValueError("gradient sinks need the hash grids on the CPU and one process")
    groups = [{"params": tables, "lr": lr_grid, "base_lr": lr_grid},
              {"params": mlp, "lr": lr_mlp, "base_lr": lr_mlp}]
    kw = dict(betas=(0.9, 0.99), eps=1e-15, fused=True)
    if not (possible if sink is None else sink):
        for g in grids:
            g.use_gradient_sink(False)
        return torch.optim.Adam(groups, **kw)
    return GridAdam(groups, grids, **kw)
