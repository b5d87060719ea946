"""``python -m rlpipe [overrides]`` (also ``rlpipe`` on the PATH): ``--help`` here, before
Hydra loads; everything else is the train command, :mod:`rlpipe.command`."""

from __future__ import annotations

import sys


def main() -> None:
    """Console entry point: ``--help`` (ours; Hydra's own: ``--hydra-help``), or the command."""
    if {"-h", "--help"} & set(sys.argv[1:]):
        from rlpipe.help import help_text

        print(help_text())
        return
    from rlpipe.command import main as command

    command()


if __name__ == "__main__":
    main()
