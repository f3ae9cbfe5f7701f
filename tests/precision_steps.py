"""One optimiser step of a model in bf16 and of an exact copy in fp32: the shared part of each trainer's bf16
autocast test (the SMLM's and the tokenizer's)."""
from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch


def bf16_and_fp32_steps(model: torch.nn.Module, twin: torch.nn.Module, batch: Any, step: Callable[..., dict],
                        hooked: Callable[[torch.nn.Module], torch.nn.Module],
                        optimizer: type[torch.optim.Optimizer] = torch.optim.Adam
                        ) -> dict[str, tuple[dict, list[torch.dtype]]]:
    """``{precision: (stats of step(model, batch, optim, sched, precision), dtypes of hooked(model)'s outputs)}``
    after one step of ``model`` in bf16 and of ``twin`` in fp32 (lr 1e-3, constant schedule)."""
    out = {}
    for precision, m in (("bf16", model), ("fp32", twin)):
        optim = optimizer(m.parameters(), lr=1e-3)
        sched = torch.optim.lr_scheduler.LambdaLR(optim, lambda s: 1.0)
        dtypes: list[torch.dtype] = []
        hook = hooked(m).register_forward_hook(lambda mod, args, result: dtypes.append(result.dtype))
        try:
            stats = step(m, batch, optim, sched, precision)
        finally:
            hook.remove()
        out[precision] = (stats, dtypes)
    return out
