"""The studies: scripts that measure the tool, run from the repository root as modules
(``python -m studies.NAME``); one study imports another as ``from studies import NAME``."""
