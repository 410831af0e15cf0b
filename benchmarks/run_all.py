"""Run the benchmarks and write docs/benchmarks.md from what they print: no figure is typed by hand.

    python benchmarks/run_all.py                      # every benchmark (the simulator's GalSim peer alone is ~10 min)
    python benchmarks/run_all.py --only simulator     # one section; the others are kept as they were
    python benchmarks/run_all.py --list

Each section of docs/benchmarks.md is one run of one script: the date, the machine (CPU model,
cores, memory, load average before and after, BLAS and its threads), the code's commit, the exact
command, the lines that state the run's ratios, and the script's whole output. Ratios are measured
within that run; comparing figures from two sections compares two runs (and two machine states).
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import re
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DOCUMENT = ROOT / "docs" / "benchmarks.md"


@dataclass(frozen=True)
class Benchmark:
    name: str
    title: str
    arguments: tuple[str, ...]
    #: Lines of the output that state the run's ratios and headline figures (shown as the summary).
    summary: str


BENCHMARKS = (
    Benchmark(
        "simulator",
        "The simulator against the GalSim pipeline: the paper's Fig. 3 grid",
        ("benchmarks/bench_simulator.py",),
        r"RATIO|from the shell|BLAS|largest difference",
    ),
    Benchmark(
        "solver",
        "The calculator: a solve from the tables against the same slope from GalSim",
        ("benchmarks/bench_solver.py",),
        r"[Rr]atio|median|×|x\b",
    ),
    Benchmark(
        "default",
        "The Roman default's answers against the paper tables': CPU per answer, a batch, the page's limits",
        ("benchmarks/bench_default.py",),
        r"RATIO|batch|limits",
    ),
    Benchmark(
        "scene",
        "Cost of each scene effect relative to the plain simulation",
        ("benchmarks/bench_scene.py",),
        r"^(configuration|plain|roman preset|everything)\b",
    ),
    Benchmark(
        "ramps",
        "Up the ramp against the final frame",
        ("benchmarks/bench_ramps.py",),
        r"\bx ?\d",
    ),
    Benchmark(
        "field_tables",
        "One Roman-default field-grid table against the paper's table",
        ("benchmarks/bench_field_tables.py",),
        r"the paper's",
    ),
    Benchmark(
        "job_memory",
        "Peak memory of a simulation job per stamp pixel",
        ("benchmarks/bench_job_memory.py",),
        r"per stamp pixel|baseline|bytes",
    ),
    Benchmark(
        "service",
        "Load on the service: table solves while simulations run, and the Roman default's solves",
        ("benchmarks/bench_service.py",),
        r"req/s|p99|target",
    ),
    Benchmark(
        "service_throughput",
        "The Roman default's mix against the paper tables' solves on the service, idle, alternating",
        ("benchmarks/bench_service.py", "--only-throughput", "--duration", "5"),
        r"RATIO|^p99 of",
    ),
    Benchmark(
        "service_cpu",
        "The Roman default's mix against the paper tables' solves through the service app: CPU per request, one process",
        ("benchmarks/bench_service_cpu.py",),
        r"RATIO|ms",
    ),
)


def _read(path: str, key: str) -> str | None:
    try:
        for line in Path(path).read_text().splitlines():
            if line.startswith(key):
                return line.split(":", 1)[1].strip()
    except OSError:
        return None
    return None


def _versions() -> str:
    code = (
        "import numpy, sys; out = [f'Python {sys.version.split()[0]}', f'numpy {numpy.__version__}']\n"
        "try:\n import galsim; out.append(f'GalSim {galsim.__version__}')\nexcept ImportError: out.append('no GalSim')\n"
        "from threadpoolctl import threadpool_info\n"
        "out += [f\"BLAS {b['internal_api']} {b['version']} ({b['num_threads']} threads by default)\""
        " for b in threadpool_info() if b['user_api'] == 'blas']\n"
        "print(', '.join(out))"
    )
    environment = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=environment, check=False)
    return done.stdout.strip() or done.stderr.strip().splitlines()[-1]


def _commit() -> str:
    done = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=False)
    dirty = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain"], capture_output=True, text=True, check=False)
    commit = done.stdout.strip() or "unknown"
    return commit + (" (with uncommitted changes)" if dirty.stdout.strip() else "")


def machine() -> str:
    """One line naming the machine this run is on."""
    memory = _read("/proc/meminfo", "MemTotal")
    memory_gb = f"{int(memory.split()[0]) / 1024**2:.0f} GB" if memory else "memory unknown"
    cpu = _read("/proc/cpuinfo", "model name") or platform.processor() or platform.machine()
    threads = os.environ.get("NLPSF_BLAS_THREADS")
    pinned = sorted(k for k in os.environ if k.endswith("_NUM_THREADS"))
    return (
        f"{cpu}, {os.cpu_count()} cores, {memory_gb}, {platform.system()} {platform.release()}; {_versions()}; "
        f"NLPSF_BLAS_THREADS {'= ' + threads if threads else 'unset (the kernels use 1 BLAS thread)'}; "
        + (f"environment sets {', '.join(pinned)}" if pinned else "no *_NUM_THREADS in the environment")
    )


def run(benchmark: Benchmark, extra: list[str]) -> str:
    """Run one benchmark and return its section of the document."""
    command = [sys.executable, *benchmark.arguments, *extra]
    shown = "python " + " ".join([*benchmark.arguments, *extra])
    started = datetime.datetime.now(datetime.UTC)
    load_before = os.getloadavg()[0]
    wall = time.perf_counter()
    done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - wall
    load_after = os.getloadavg()[0]
    output = done.stdout.rstrip()
    if done.returncode:
        output += f"\n\n[exit status {done.returncode}]\n" + done.stderr.rstrip()[-4000:]
    summary = [line.strip() for line in output.splitlines() if re.search(benchmark.summary, line)]
    lines = [
        f"## {benchmark.title}",
        "",
        f"`{shown}`, run {started:%Y-%m-%d %H:%M} UTC ({wall:.0f} s wall) at commit {_commit()}.",
        "",
        f"Machine: {machine()}. Load average {load_before:.1f} at the start, {load_after:.1f} at the end"
        + (" (a busy machine: wall times are inflated, CPU-time ratios much less so)." if load_before > 1 else "."),
        "",
    ]
    if summary:
        lines += ["What the run states:", "", "```text", *summary[:20], "```", ""]
    lines += ["The whole output:", "", "```text", output, "```"]
    return "\n".join(lines)


HEADER = """# Benchmarks

This file is written by `python benchmarks/run_all.py` (one section: `--only NAME`) from what the
scripts in `benchmarks/` print; do not edit it by hand. Each section is one run: its ratios are
measured within that run, against peers run in the same process or the same minute, on the machine
it names. Figures from different sections come from different runs. The design goals these measure
(the shell's Fig. 3 grid at least 300x cheaper in CPU than the paper's GalSim pipeline; the service
at 2000 requests/s and p99 < 20 ms while simulations run) are stated in the scripts' docstrings.
"""


def _marker(name: str, end: bool = False) -> str:
    return f"<!-- {'/' if end else ''}benchmark:{name} -->"


def _not_run(benchmark: Benchmark) -> str:
    return (
        f"## {benchmark.title}\n\nNot measured yet in this file: "
        f"`python benchmarks/run_all.py --only {benchmark.name}` writes this section."
    )


def write(sections: dict[str, str]) -> None:
    """Replace the named sections, keep the others as the file has them, in the benchmarks' order."""
    text = DOCUMENT.read_text() if DOCUMENT.exists() else ""
    blocks = []
    for benchmark in BENCHMARKS:
        body = sections.get(benchmark.name)
        if body is None:
            found = re.search(
                re.escape(_marker(benchmark.name)) + r"\n(.*?)\n" + re.escape(_marker(benchmark.name, end=True)), text, re.S
            )
            body = found.group(1) if found else _not_run(benchmark)
        blocks.append(f"{_marker(benchmark.name)}\n{body}\n{_marker(benchmark.name, end=True)}")
    DOCUMENT.parent.mkdir(exist_ok=True)
    DOCUMENT.write_text(HEADER + "\n" + "\n\n".join(blocks) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--only", action="append", choices=[b.name for b in BENCHMARKS], help="this benchmark only (repeat)")
    parser.add_argument("--list", action="store_true", help="name the benchmarks and stop")
    parser.add_argument("extra", nargs="*", help="arguments passed to the one benchmark --only names (after --)")
    args = parser.parse_args()
    if args.list:
        for b in BENCHMARKS:
            print(f"{b.name:<12} {' '.join(b.arguments)}  {b.title}")
        return
    chosen = [b for b in BENCHMARKS if not args.only or b.name in args.only]
    if args.extra and len(chosen) != 1:
        parser.error("extra arguments go to one benchmark: name it with --only")
    for benchmark in chosen:
        print(f"running {benchmark.name} ...", file=sys.stderr, flush=True)
        write({benchmark.name: run(benchmark, args.extra)})  # each section is saved as soon as it is measured
    print(f"wrote {DOCUMENT.relative_to(ROOT)}", file=sys.stderr)


if __name__ == "__main__":
    main()
