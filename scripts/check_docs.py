"""Run the commands the documents show and compare what they print with what the documents say.

    python scripts/check_docs.py                    # README.md and docs/guide.md
    python scripts/check_docs.py docs/api.md        # any markdown files

A ```console block holds commands (lines starting ``$ ``; a trailing backslash continues one) each
followed by the output it prints. An output line matches when it is equal, or where it holds ``…``,
when the rest matches with ``…`` standing for any text (timings, for instance); a line that is only
``…`` stands for any number of lines. A command shown with no output must exit with status 0.
Commands run from the repository root with this interpreter's ``bin/`` first on PATH, so ``nlpsf``
and ``python`` are the environment's own. Commands that talk to ``localhost:8000`` get a service
started for them (``nlpsf serve`` on a free port, substituted in). ```sh blocks are not run: they
hold placeholders (a scheduler's address, your own files) or install software.
"""

from __future__ import annotations

import argparse
import os
import re
import socket
import subprocess
import sys
import time
import urllib.request
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_FILES = ("README.md", "docs/guide.md")
ELLIPSIS = "…"


@dataclass(frozen=True)
class Example:
    source: str
    line: int
    command: str
    expected: tuple[str, ...]


def examples(path: Path) -> list[Example]:
    """Every command of every ```console block, with the output shown under it."""
    out: list[Example] = []
    lines = path.read_text().splitlines()
    k = 0
    while k < len(lines):
        if lines[k].strip() != "```console":
            k += 1
            continue
        k += 1
        command: list[str] | None = None
        start = 0
        expected: list[str] = []
        while k < len(lines) and lines[k].strip() != "```":
            text = lines[k]
            if text.startswith("$ "):
                if command is not None:
                    out.append(Example(path.name, start, "\n".join(command), tuple(expected)))
                command, start, expected = [text[2:]], k + 1, []
                while command[-1].endswith("\\") and k + 1 < len(lines):
                    k += 1
                    command.append(lines[k])
            elif command is not None:
                expected.append(text)
            k += 1
        if command is not None:
            out.append(Example(path.name, start, "\n".join(command), tuple(expected)))
        k += 1
    return out


def _pattern(line: str) -> re.Pattern:
    return re.compile("^" + ".*".join(re.escape(part) for part in line.split(ELLIPSIS)) + "$")


def matches(expected: tuple[str, ...], actual: list[str]) -> bool:
    """Whether the printed lines fit the shown ones (``…`` as described in the module docstring)."""
    if not expected:
        return not actual
    head, rest = expected[0], expected[1:]
    if head.strip() == ELLIPSIS:
        return any(matches(rest, actual[k:]) for k in range(len(actual) + 1))
    if not actual:
        return False
    fits = actual[0] == head or (ELLIPSIS in head and _pattern(head).match(actual[0]) is not None)
    return fits and matches(rest, actual[1:])


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Service:
    """``nlpsf serve`` on a free port, started on first need."""

    def __init__(self, environment: dict):
        self.environment = environment
        self.process: subprocess.Popen | None = None
        self.port = 0

    def address(self) -> str:
        if self.process is None:
            self.port = _free_port()
            state = Path(os.environ.get("TMPDIR", "/tmp")) / f"nlpsf-check-docs-{self.port}.sqlite3"
            environment = {**self.environment, "NLPSF_DB_PATH": str(state), "NLPSF_WORKERS": "1"}
            command = ["nlpsf", "serve", "--port", str(self.port)]
            quiet = subprocess.DEVNULL
            self.process = subprocess.Popen(command, cwd=ROOT, env=environment, stdout=quiet, stderr=quiet)
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                try:
                    urllib.request.urlopen(f"http://127.0.0.1:{self.port}/api/v1/health", timeout=1)
                    break
                except OSError:
                    time.sleep(0.2)
            else:
                raise RuntimeError("nlpsf serve did not answer within 60 s")
        return f"localhost:{self.port}"

    def stop(self) -> None:
        if self.process is not None:
            self.process.terminate()
            self.process.wait(timeout=30)


def run(example: Example, environment: dict, service: Service, cwd: Path = ROOT) -> tuple[bool, str]:
    """Run one example in ``cwd`` (the repository root unless a test gives a folder of its own, for examples
    that write files) and compare what it prints with what the document shows."""
    command = example.command
    if "localhost:8000" in command:
        command = command.replace("localhost:8000", service.address())
    done = subprocess.run(["bash", "-c", command], cwd=cwd, env=environment, capture_output=True, text=True, check=False)
    printed = done.stdout.rstrip("\n").splitlines()
    if done.returncode != 0:
        return False, f"exit status {done.returncode}\n{done.stderr.strip()[-2000:]}"
    if example.expected and not matches(example.expected, printed):
        return False, "printed:\n" + "\n".join(printed) + "\n\nthe document shows:\n" + "\n".join(example.expected)
    return True, ""


def environment() -> dict:
    bin_dir = str(Path(sys.executable).parent)
    return {**os.environ, "PATH": bin_dir + os.pathsep + os.environ.get("PATH", ""), "COLUMNS": "100"}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("files", nargs="*", default=list(DEFAULT_FILES))
    args = parser.parse_args()
    env = environment()
    service = Service(env)
    failures = 0
    try:
        for name in args.files:
            for example in examples(ROOT / name):
                ok, why = run(example, env, service)
                print(f"{'ok  ' if ok else 'FAIL'} {example.source}:{example.line}: {example.command.splitlines()[0][:100]}")
                if not ok:
                    failures += 1
                    print("    " + why.replace("\n", "\n    "))
    finally:
        service.stop()
    print(f"{failures} failed" if failures else "every command ran and printed what the documents show")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
