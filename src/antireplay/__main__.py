"""``python -m antireplay`` is the ``antireplay`` command."""

from antireplay.cli import main

main()
