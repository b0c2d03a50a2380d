"""The official-library OpenIGTLink client (tests/igtl_client/tissuecast_igtl_client.cxx):
where its build needs are, and its build with g++ against Debian's libopenigtlink-dev. Used by
tests/serve/test_serve_cpp_client.py and benchmarks/igtl_latency.py."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

SOURCE = Path(__file__).resolve().parent / "igtl_client" / "tissuecast_igtl_client.cxx"
INCLUDE = Path("/usr/include/openigtlink")
LIBRARY = "OpenIGTLink"


def missing() -> str | None:
    """Why the client cannot be built here (the Debian package to install), or None."""
    if shutil.which("g++") is None:
        return "g++ not found (Debian package g++)"
    if not (INCLUDE / "igtlPolyDataMessage.h").is_file():
        return f"OpenIGTLink headers not found in {INCLUDE} (Debian package libopenigtlink-dev)"
    return None


def build(folder: Path, optimise: str = "-O2") -> Path:
    """The client compiled into ``folder``; raises CalledProcessError with the compiler's output."""
    binary = Path(folder) / "tissuecast_igtl_client"
    subprocess.run(["g++", optimise, "-o", str(binary), str(SOURCE), f"-I{INCLUDE}", f"-l{LIBRARY}"],
                   check=True, capture_output=True, text=True, timeout=300)
    return binary
