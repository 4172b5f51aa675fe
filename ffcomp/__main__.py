"""``python -m ffcomp`` runs the command line."""

from ffcomp.cli import main

main()
