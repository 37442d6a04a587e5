"""``python -m ewb_ident`` runs the command line."""

from .cli import main

main()
