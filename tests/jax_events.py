"""What JAX traces while a function runs, from its monitoring events (public API)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax


def traces_while(fn: Callable[[], Any]) -> list[str | None]:
    """The functions JAX traces while ``fn()`` runs (names from the monitoring events)."""
    traces: list[str | None] = []

    def listen(event: str, duration: float, **kw: Any) -> None:
        if event.endswith("jaxpr_trace_duration"):
            traces.append(kw.get("fun_name"))

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        fn()
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    return traces
