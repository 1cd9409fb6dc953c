"""Cross-compile an exported step for a Cortex-M and run it under QEMU.

:func:`run_on_target` takes a folder written by :func:`~safestab.export.export_c` with its
harness (:func:`~safestab.export.write_harness`) and, for a :data:`TARGETS` entry:

1. cross-compiles the step with ``arm-none-eabi-gcc`` (``-O2 -ffp-contract=off``, the
   target's FPU, ``-fstack-usage -fcallgraph-info=su``) and reports the step's flash and RAM
   (``arm-none-eabi-size`` of the object, and of a minimal firmware image: start-up code, a
   loop calling the step, no C library I/O) and its worst stack depth (the deepest path of
   the call graph from ``<name>_step``, from GCC's per-function frame sizes);
2. runs the recorded harness under ``qemu-system-arm`` on an MPS2 board model (semihosting
   for its output): the step on the microcontroller against the JAX step;
3. runs a bench program under QEMU with ``-icount shift=0`` (the virtual clock advances one
   nanosecond per executed instruction) that times every recorded state with the SysTick
   timer, calibrated in the same run by a loop of known instruction count, measures the
   stack the step actually used (the stack painted with a pattern below the caller), and
   prints a hash of every output's bits per state; the same program built for the host
   prints the host's hashes, so agreement with the host is counted bit for bit.

What QEMU counts is instructions, not cycles: on a Cortex-M4 most instructions of this
code take one cycle, divisions and square roots 14, loads from slow flash more; the count
is a budget figure (instructions per step against a cycle budget), not a timing.
"""

from __future__ import annotations

import dataclasses
import re
import shutil
import subprocess
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import CompilationError, ParameterError
from .exporter import ExportedC

__all__ = [
    "PACKAGES",
    "TARGETS",
    "EmbeddedReport",
    "Target",
    "export_for_target",
    "find_toolchain",
    "run_on_target",
]

#: Debian packages of the cross toolchain and the emulator.
PACKAGES = ("gcc-arm-none-eabi", "libnewlib-arm-none-eabi", "qemu-system-arm")


@dataclasses.dataclass(frozen=True)
class Target:
    """A Cortex-M core, its compiler flags and the QEMU board that emulates it."""

    name: str
    precision: str  #: the export's precision that matches the FPU
    cflags: tuple[str, ...]
    machine: str  #: QEMU board model
    cpu: str  #: QEMU CPU model
    description: str


TARGETS = {
    "cortex-m4": Target(
        "cortex-m4",
        "float",
        ("-mcpu=cortex-m4", "-mthumb", "-mfloat-abi=hard", "-mfpu=fpv4-sp-d16"),
        "mps2-an386",
        "cortex-m4",
        "Cortex-M4F (single-precision FPU), QEMU MPS2 AN386",
    ),
    "cortex-m7": Target(
        "cortex-m7",
        "double",
        ("-mcpu=cortex-m7", "-mthumb", "-mfloat-abi=hard", "-mfpu=fpv5-d16"),
        "mps2-an500",
        "cortex-m7",
        "Cortex-M7 with double-precision FPU (FPv5-D16), QEMU MPS2 AN500",
    ),
}

_TOOLS = {
    "gcc": ("arm-none-eabi-gcc", "gcc-arm-none-eabi"),
    "size": ("arm-none-eabi-size", "gcc-arm-none-eabi"),
    "qemu": ("qemu-system-arm", "qemu-system-arm"),
}
_OPT = ("-std=c99", "-O2", "-ffp-contract=off", "-fno-math-errno", "-Wall", "-Wextra")


@dataclasses.dataclass(frozen=True)
class EmbeddedReport:
    """What :func:`run_on_target` measured (sizes in bytes)."""

    target: str
    precision: str
    step_text: int  #: code and constants of the step's object file (flash)
    step_data: int  #: initialised data of the step's object (flash and RAM)
    step_bss: int  #: zeroed data of the step's object (RAM)
    firmware_flash: int  #: text + data of a minimal firmware image (start-up, loop, step)
    firmware_ram: int  #: data + bss of that image, the stack not included
    stack_static: int  #: deepest call path from the step, from GCC's frame sizes
    stack_measured: int  #: the most stack the step touched on the recorded states
    library_calls: tuple[str, ...]  #: functions the step calls outside its file
    states: int
    harness_mismatches: int  #: against the JAX step, at the precision's tolerance
    harness_output: str
    instructions_max: int
    instructions_median: int
    instructions_min: int
    bit_identical_to_host: int  #: states whose outputs' bits equal the host build's
    flags: tuple[str, ...]

    def row(self) -> dict[str, Any]:
        """The report as a JSON-ready dict."""
        out = dataclasses.asdict(self)
        out.pop("harness_output")
        out["library_calls"] = list(self.library_calls)
        out["flags"] = list(self.flags)
        return out


def find_toolchain(install: bool = True) -> dict[str, str]:
    """Paths of ``arm-none-eabi-gcc``, ``arm-none-eabi-size`` and ``qemu-system-arm``.

    Where one is missing and ``install`` is true, installs :data:`PACKAGES` with ``apt-get``
    when this process may (root, apt-get present).

    Raises
    ------
    CompilationError
        Naming what is missing and the packages (or commands) that provide it.
    """
    found = {key: shutil.which(exe) for key, (exe, _) in _TOOLS.items()}
    if install and not all(found.values()) and shutil.which("apt-get") and _is_root():
        env = {"DEBIAN_FRONTEND": "noninteractive", "PATH": _path()}
        for cmd in (["apt-get", "install", "-y", "-qq", *PACKAGES], ["apt-get", "update", "-qq"],
                    ["apt-get", "install", "-y", "-qq", *PACKAGES]):  # fmt: skip
            try:  # bounded: a machine without a reachable package mirror must not hang here
                done = subprocess.run(cmd, capture_output=True, env=env, check=False, timeout=600)
            except subprocess.TimeoutExpired:
                break
            if done.returncode == 0 and cmd[1] == "install":
                break
        found = {key: shutil.which(exe) for key, (exe, _) in _TOOLS.items()}
    missing = [key for key, path in found.items() if not path]
    if missing:
        names = ", ".join(_TOOLS[k][0] for k in missing)
        pkgs = " ".join(sorted({_TOOLS[k][1] for k in missing} | {"libnewlib-arm-none-eabi"}))
        raise CompilationError(
            f"the embedded build needs {names}, not found on PATH; on Debian or Ubuntu: "
            f"sudo apt-get install {pkgs} (elsewhere: the Arm GNU Toolchain and QEMU)"
        )
    return {key: str(path) for key, path in found.items()}


def _is_root() -> bool:
    import os

    return hasattr(os, "geteuid") and os.geteuid() == 0


def _path() -> str:
    import os

    return os.environ.get("PATH", "/usr/sbin:/usr/bin:/sbin:/bin")


# -- the support files ---------------------------------------------------------------------

_LINKER = """/* MPS2 boards under QEMU: code in SSRAM1 at 0 (the flash of a real part), data at
 * 0x20000000. The stack starts at the top of RAM and grows down. */
MEMORY
{
  FLASH (rx)  : ORIGIN = 0x00000000, LENGTH = 4M
  RAM   (rwx) : ORIGIN = 0x20000000, LENGTH = 4M
}
ENTRY(Reset_Handler)
SECTIONS
{
  .isr_vector : { KEEP(*(.isr_vector)) } > FLASH
  .text : { *(.text*) *(.rodata*) KEEP(*(.init)) KEEP(*(.fini)) } > FLASH
  .ARM.exidx : { *(.ARM.exidx*) } > FLASH
  __etext = .;
  .data : { __data_start__ = .; *(.data*) . = ALIGN(4); __data_end__ = .; } > RAM AT > FLASH
  .bss (NOLOAD) : { __bss_start__ = .; *(.bss*) *(COMMON) . = ALIGN(4); __bss_end__ = .; } > RAM
  end = .;
  _end = .;
  __stack_top = ORIGIN(RAM) + LENGTH(RAM);
}
"""

_STARTUP = """/* Minimal Cortex-M start-up: vector table, FPU on, .data copied, .bss zeroed, main().
 * With SS_SEMIHOSTING, the C library's output and exit go to the debugger (QEMU). */
#include <stdint.h>
extern uint32_t __etext, __data_start__, __data_end__, __bss_start__, __bss_end__;
extern uint32_t __stack_top;
extern int main(void);
void Reset_Handler(void);
#ifdef SS_SEMIHOSTING
#include <stdlib.h>
extern void initialise_monitor_handles(void);
static void Fault_Handler(void) { exit(3); }
#else
static void Fault_Handler(void) { for (;;) {} }
#endif
__attribute__((section(".isr_vector"), used)) static const void *const vectors[16] = {
    &__stack_top, (const void *)Reset_Handler, (const void *)Fault_Handler,
    (const void *)Fault_Handler, (const void *)Fault_Handler, (const void *)Fault_Handler,
    (const void *)Fault_Handler};
void Reset_Handler(void)
{
    volatile uint32_t *cpacr = (volatile uint32_t *)0xE000ED88u;
    *cpacr |= 0xFu << 20; /* CP10 and CP11: full access to the FPU */
    __asm volatile("dsb\\n isb");
    uint32_t *src = &__etext, *dst = &__data_start__;
    while (dst < &__data_end__) *dst++ = *src++;
    for (dst = &__bss_start__; dst < &__bss_end__;) *dst++ = 0;
#ifdef SS_SEMIHOSTING
    initialise_monitor_handles();
    exit(main());
#else
    main();
    for (;;) {}
#endif
}
void _init(void) {}
void _fini(void) {}
"""


def _firmware(name: str, exported: ExportedC) -> str:
    real = exported.precision
    up = name.upper()
    return f"""/* A minimal firmware: the step in a loop, inputs and outputs through volatile memory
 * (what a 1 kHz control task does, without the sensor and actuator drivers). */
#include "{name}.h"
volatile {real} x_in[{up}_N_STATES];
volatile {real} u_out[{up}_N_OUT];
volatile int status_out;
int main(void)
{{
    {real} x[{up}_N_STATES], u[{up}_N_OUT];
    for (;;) {{
        for (int i = 0; i < {up}_N_STATES; ++i) x[i] = x_in[i];
        status_out = {name}_step(x, u, 0);
        for (int j = 0; j < {up}_N_OUT; ++j) u_out[j] = u[j];
    }}
}}
"""


def _bench(name: str, exported: ExportedC, states: np.ndarray) -> str:
    from ._cgen import Emitter

    e = Emitter(exported.precision)
    real, up = e.real, name.upper()
    items = ", ".join(e.lit(v, np.float64) for v in states.reshape(-1))
    prim = exported.leaves[exported.primary]
    feed = []
    for i, leaf in enumerate(exported.leaves):
        if leaf.size == 0:
            continue
        if i == exported.primary:
            ref, n = f"{prim.name}", leaf.size
        elif leaf.shape == ():
            ref, n = f"&info.{leaf.name}", 1
        else:
            ref, n = f"info.{leaf.name}", leaf.size
        ct = e.io_ctype(leaf.dtype)
        feed.append(f"        h = mix(h, (const unsigned char *){ref}, {n} * sizeof({ct}));")
    return f"""/* {name}_bench.c: per recorded state, the instructions the step takes (QEMU -icount,
 * SysTick calibrated by a loop of known length), the stack it touches, and a hash of the bits
 * of every output. Built for the host with -DSS_HOST: the hashes only. */
#include <stdint.h>
#include <stdio.h>
#include "{name}.h"

#define N_CASES {len(states)}
static const {real} states[N_CASES * {up}_N_STATES] = {{{items}}};

static uint32_t mix(uint32_t h, const unsigned char *p, unsigned long n)
{{
    for (unsigned long i = 0; i < n; ++i) h = (h ^ p[i]) * 16777619u; /* FNV-1a */
    return h;
}}

#ifndef SS_HOST
#define SYST_CSR (*(volatile uint32_t *)0xE000E010u)
#define SYST_RVR (*(volatile uint32_t *)0xE000E014u)
#define SYST_CVR (*(volatile uint32_t *)0xE000E018u)
#define PAINT_WORDS 65536u
#define PAINT 0xA5A5A5A5u

static uint32_t now(void) {{ return SYST_CVR; }}
static uint32_t since(uint32_t t0) {{ return (t0 - SYST_CVR) & 0xFFFFFFu; }}

__attribute__((noinline)) static uint32_t spin(uint32_t n)
{{
    const uint32_t t0 = now();
    __asm volatile("1: subs %0, %0, #1\\n bne 1b" : "+r"(n) : : "cc");
    return since(t0);
}}

__attribute__((noinline)) static uint32_t timed(const {real} *x, {real} *u, {name}_info *info,
                                                 uint32_t *ticks)
{{
    uint32_t *sp;
    __asm volatile("mov %0, sp" : "=r"(sp));
    uint32_t *lo = sp - PAINT_WORDS;
    for (uint32_t *p = lo; p < sp - 32; ++p) *p = PAINT;
    const uint32_t t0 = now();
    {name}_step(x, u, info);
    *ticks = since(t0);
    uint32_t *p = lo;
    while (p < sp && *p == PAINT) ++p;
    return (uint32_t)((char *)sp - (char *)p);
}}
#endif

int main(void)
{{
#ifndef SS_HOST
    SYST_RVR = 0xFFFFFFu;
    SYST_CVR = 0u;
    SYST_CSR = 5u; /* enabled, processor clock, no interrupt */
    const uint32_t loop = 200000u;
    printf("calibration %lu instructions %lu ticks %lu ticks0\\n", (unsigned long)(2u * loop),
           (unsigned long)spin(loop), (unsigned long)spin(1u));
#endif
    for (long k = 0; k < N_CASES; ++k) {{
        {e.io_ctype(prim.dtype)} {prim.name}[{up}_N_OUT];
        {name}_info info;
        uint32_t h = 2166136261u, ticks = 0, stack = 0;
#ifndef SS_HOST
        stack = timed(states + k * {up}_N_STATES, {prim.name}, &info, &ticks);
#else
        {name}_step(states + k * {up}_N_STATES, {prim.name}, &info);
#endif
{chr(10).join(feed)}
        printf("state %ld hash %08lx ticks %lu stack %lu\\n", k, (unsigned long)h,
               (unsigned long)ticks, (unsigned long)stack);
    }}
    return 0;
}}
"""


# -- build and run ------------------------------------------------------------------------


def _run(cmd: list[str], cwd: Path, what: str, timeout: float = 600) -> str:
    proc = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=timeout)
    if proc.returncode != 0:
        raise CompilationError(
            f"{what} failed (exit {proc.returncode}): {' '.join(cmd)}\n"
            + (proc.stderr or proc.stdout)[-4000:]
        )
    return proc.stdout


def _qemu(tools: dict[str, str], target: Target, elf: str, cwd: Path, icount: bool) -> str:
    cmd = [tools["qemu"], "-M", target.machine, "-cpu", target.cpu, "-nographic"]
    cmd += ["-monitor", "none", "-serial", "none"]
    cmd += ["-semihosting-config", "enable=on,target=native", "-kernel", elf]
    if icount:
        cmd += ["-icount", "shift=0,align=off,sleep=off"]
    proc = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=600)
    return proc.stdout + proc.stderr


def _sizes(tools: dict[str, str], path: Path) -> tuple[int, int, int]:
    out = _run([tools["size"], path.name], path.parent, "arm-none-eabi-size")
    text, data, bss = (int(v) for v in out.strip().splitlines()[-1].split()[:3])
    return text, data, bss


def _stack_depth(ci_path: Path, root: str) -> tuple[int, tuple[str, ...]]:
    """The deepest path of GCC's call graph (``-fcallgraph-info=su``) from ``root``."""
    text = ci_path.read_text()
    size: dict[str, int] = {}
    for title, label in re.findall(r'node: \{ title: "([^"]+)" label: "([^"]*)"', text):
        m = re.search(r"(\d+) bytes", label)
        if m:
            size[title] = int(m.group(1))
    edges: dict[str, list[str]] = {}
    for src, dst in re.findall(r'edge: \{ sourcename: "([^"]+)" targetname: "([^"]+)"', text):
        edges.setdefault(src, []).append(dst)
    external: set[str] = set()

    def depth(fn: str, seen: tuple[str, ...]) -> int:
        if fn in seen:
            raise CompilationError(f"the step is recursive ({' -> '.join((*seen, fn))})")
        if fn not in size:
            external.add(fn)
            return 0
        return size[fn] + max((depth(g, (*seen, fn)) for g in edges.get(fn, [])), default=0)

    return depth(root, ()), tuple(sorted(external))


def run_on_target(
    folder: str | Path,
    name: str,
    exported: ExportedC,
    states: Any,
    target: str,
    *,
    install: bool = True,
    progress: Callable[[str], None] | None = None,
) -> EmbeddedReport:
    """Build ``<name>.c`` and its harness for ``target``, run them under QEMU, measure.

    Parameters
    ----------
    folder : path
        Holds ``<name>.c``, ``<name>.h`` and ``<name>_harness.c``; the target's build goes
        to ``folder/<target>/``. A relative path is taken against the current working
        folder when the function is called.
    name : str
    exported : ExportedC
        What :func:`~safestab.export.export_c` returned for these files.
    states : array of shape (N, n)
        The harness's recorded states (the bench times the step on each).
    target : {"cortex-m4", "cortex-m7"}
    install : bool
        Install the toolchain with apt-get where it is missing and this process may.
    progress : callable, optional

    Returns
    -------
    EmbeddedReport

    Raises
    ------
    ParameterError
        If ``target`` is unknown.
    CompilationError
        If a tool is missing (named, with its package), a build fails, or QEMU prints no
        result.
    """
    if target not in TARGETS:
        raise ParameterError(f"target must be one of {sorted(TARGETS)}, got {target!r}")
    tgt = TARGETS[target]
    say = progress or (lambda msg: None)
    tools = find_toolchain(install=install)
    src = Path(folder).absolute()  # the tools run with the build folder as their cwd
    build = src / target
    build.mkdir(parents=True, exist_ok=True)
    for f in (f"{name}.c", f"{name}.h", f"{name}_harness.c"):
        shutil.copyfile(src / f, build / f)
    states = np.asarray(states, dtype=np.float64)
    (build / "link.ld").write_text(_LINKER)
    (build / "startup.c").write_text(_STARTUP)
    (build / f"{name}_firmware.c").write_text(_firmware(name, exported))
    (build / f"{name}_bench.c").write_text(_bench(name, exported, states))
    gcc = [tools["gcc"], *tgt.cflags]
    say(f"cross-compiling for {tgt.description}")
    step_flags = [*_OPT, "-fstack-usage", "-fcallgraph-info=su", "-ffunction-sections"]
    _run([*gcc, *step_flags, "-c", f"{name}.c", "-o", f"{name}.o"], build, "compiling the step")
    text, data, bss = _sizes(tools, build / f"{name}.o")
    stack_static, calls = _stack_depth(build / f"{name}.ci", f"{name}_step")

    semi = ["-DSS_SEMIHOSTING", "-nostartfiles", "--specs=rdimon.specs", "-T", "link.ld"]
    bare = ["-nostartfiles", "--specs=nano.specs", "--specs=nosys.specs", "-T", "link.ld"]
    _run(
        [*gcc, *_OPT, *bare, "-ffunction-sections", "-fdata-sections", "-Wl,--gc-sections",
         "startup.c", f"{name}.c", f"{name}_firmware.c", "-lm", "-o", f"{name}_firmware.elf"],
        build, "linking the firmware image",
    )  # fmt: skip
    fw_text, fw_data, fw_bss = _sizes(tools, build / f"{name}_firmware.elf")
    for prog in ("harness", "bench"):
        _run(
            [*gcc, *_OPT, *semi, "startup.c", f"{name}.c", f"{name}_{prog}.c", "-lm",
             "-o", f"{name}_{prog}.elf"],
            build, f"linking the {prog}",
        )  # fmt: skip
    say(f"running the harness under qemu-system-arm -M {tgt.machine}")
    harness_out = _qemu(tools, tgt, f"{name}_harness.elf", build, icount=False)
    m = re.search(r"(\d+) states, (\d+) mismatches", harness_out)
    if not m:
        raise CompilationError(f"the harness printed no result under QEMU:\n{harness_out[-2000:]}")
    mismatches = int(m.group(2))
    say("timing the step (QEMU instruction counting)")
    bench_out = _qemu(tools, tgt, f"{name}_bench.elf", build, icount=True)
    cal = re.search(r"calibration (\d+) instructions (\d+) ticks (\d+) ticks0", bench_out)
    rows = re.findall(r"state (\d+) hash ([0-9a-f]+) ticks (\d+) stack (\d+)", bench_out)
    if not cal or len(rows) != len(states):
        raise CompilationError(f"the bench printed no result under QEMU:\n{bench_out[-2000:]}")
    # instructions per SysTick tick, from the loop of known length minus the empty loop
    per_tick = int(cal.group(1)) / max(int(cal.group(2)) - int(cal.group(3)), 1)
    ticks = np.array([int(r[2]) for r in rows])
    instructions = np.rint(ticks * per_tick).astype(int)
    say("the same bench on the host, for bit agreement")
    from .native import find_compiler

    host = [find_compiler(), "-std=c99", "-O2", "-ffp-contract=off", "-DSS_HOST"]
    _run([*host, f"{name}.c", f"{name}_bench.c", "-lm", "-o", f"{name}_bench_host"], build,
         "building the host bench")  # fmt: skip
    host_out = _run([str((build / f"{name}_bench_host").resolve())], build, "the host bench")
    host_rows = re.findall(r"state (\d+) hash ([0-9a-f]+)", host_out)
    same = sum(a[1] == b[1] for a, b in zip(rows, host_rows, strict=False))
    return EmbeddedReport(
        target=target,
        precision=exported.precision,
        step_text=text,
        step_data=data,
        step_bss=bss,
        firmware_flash=fw_text + fw_data,
        firmware_ram=fw_data + fw_bss,
        stack_static=stack_static,
        stack_measured=max(int(r[3]) for r in rows),
        library_calls=calls,
        states=len(states),
        harness_mismatches=mismatches,
        harness_output=harness_out.strip(),
        instructions_max=int(instructions.max()),
        instructions_median=int(np.median(instructions)),
        instructions_min=int(instructions.min()),
        bit_identical_to_host=int(same),
        flags=(*tgt.cflags, *_OPT),
    )


def export_for_target(
    controller: Any,
    name: str,
    out: str | Path,
    states: Any,
    target: str,
    *,
    precision: str | None = None,
    description: str = "",
    install: bool = True,
    progress: Callable[[str], None] | None = None,
) -> EmbeddedReport:
    """Export any controller or safety filter for ``target`` and run :func:`run_on_target`.

    Writes ``<name>.c``, ``<name>.h`` (the target's precision, the embedded loop layout) and
    ``<name>_harness.c`` with the JAX step's outputs at ``states`` (rounded to float first
    for a float target: the comparison is of the step's arithmetic, not of its input's
    rounding), then builds and runs both on the emulated core.

    Parameters
    ----------
    controller : UniversalController or SafetyFilter
    name : str
    out : path
    states : array of shape (N, n)
    target : {"cortex-m4", "cortex-m7"}
    precision : {"double", "float"}, optional
        Default: the target's FPU (``"double"`` on a Cortex-M4F runs in software).
    description : str
        Extra text for the header.
    install, progress
        As for :func:`run_on_target`.

    Returns
    -------
    EmbeddedReport
    """
    from .exporter import export_c
    from .harness import comparison_scales, write_harness

    if target not in TARGETS:
        raise ParameterError(f"target must be one of {sorted(TARGETS)}, got {target!r}")
    precision = TARGETS[target].precision if precision is None else precision
    states = np.asarray(states, dtype=np.float64)
    if precision == "float":
        states = states.astype(np.float32).astype(np.float64)
    out = Path(out).absolute()  # once: run_on_target's tools run in a folder below it
    out.mkdir(parents=True, exist_ok=True)
    exported = export_c(
        controller, name, out, precision=precision, description=description, layout="embedded"
    )
    expected = controller.step_fn(states)
    scales = comparison_scales(controller, expected, states)
    write_harness(exported, states, expected, out, scales=scales)
    return run_on_target(out, name, exported, states, target, install=install, progress=progress)
