"""performance.md is written by several benchmark runs; each owns a block between markers."""

from __future__ import annotations

from pathlib import Path


def put_block(md_path: Path, block: str, begin: str, end: str) -> None:
    """Put ``block`` (which starts with ``begin`` and ends with ``end``) into the page.

    An existing block between the markers is replaced; otherwise the block is appended. The
    page is written atomically (a temporary file, then a rename).
    """
    text = md_path.read_text() if md_path.exists() else ""
    if begin in text and end in text:
        head, rest = text.split(begin, 1)
        text = head + block + rest.split(end, 1)[1]
    else:
        text = text.rstrip("\n") + "\n\n" + block + "\n"
    tmp = md_path.with_name(md_path.name + ".tmp")
    tmp.write_text(text)
    tmp.replace(md_path)


def update_block(md_path: Path, json_path: Path, markdown, begin: str, end: str) -> None:
    """Put the block that ``markdown(results)`` makes of the saved results into the page."""
    import json

    if json_path.exists():
        put_block(md_path, markdown(json.loads(json_path.read_text())), begin, end)


def save_results(out_dir: Path, json_name: str, results: dict, markdown, begin, end) -> None:
    """Write ``results`` as strict JSON (atomically) and put their block into performance.md."""
    import json

    out_dir.mkdir(parents=True, exist_ok=True)
    json_path = out_dir / json_name
    tmp = json_path.with_name(json_path.name + ".tmp")
    tmp.write_text(json.dumps(results, indent=2, allow_nan=False))
    tmp.replace(json_path)
    update_block(out_dir / "performance.md", json_path, markdown, begin, end)
    print(markdown(results))


def machine() -> dict:
    """Where a benchmark ran: platform, CPUs, JAX and its device, the load average."""
    import os
    import platform

    import jax

    return {
        "platform": platform.platform(),
        "cpus": os.cpu_count(),
        "jax": jax.__version__,
        "device": str(jax.devices()[0]),
        "load_average_at_start": os.getloadavg()[0],
    }


def median_us(fn, args, repeat):
    """Median time of ``fn(args[i % len(args)])`` over ``repeat`` calls (3 warm-ups), in us."""
    import time

    import numpy as np

    for x in args[:3]:
        fn(x)
    times = []
    for i in range(repeat):
        t0 = time.perf_counter()
        fn(args[i % len(args)])
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e6)


def states_per_second(fn, x, repeat=5):
    """States per second of ``fn(x)`` on a batch ``x`` (the median of ``repeat`` calls after a
    warm-up, each waited for with ``jax.block_until_ready``)."""
    import time

    import jax
    import numpy as np

    jax.block_until_ready(fn(x))
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(x))
        times.append(time.perf_counter() - t0)
    return len(x) / float(np.median(times))


def measured(r: dict) -> str:
    """ "Measured DATE, N CPUs, load average X at the start" for a result with ``machine``."""
    m = r["machine"]
    return (
        f"Measured {r['date']}, {m['cpus']} CPUs, load average "
        f"{m['load_average_at_start']:.1f} at the start"
    )
