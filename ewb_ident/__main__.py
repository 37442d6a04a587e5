"""``python -m ewb_ident`` runs the command line."""

from ewb_ident.cli import main

main()
