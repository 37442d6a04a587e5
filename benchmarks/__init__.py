"""The benchmarks: scripts that time the tool, run from the repository root as modules
(``python -m benchmarks.NAME``); one benchmark imports another as
``from benchmarks import NAME``."""
