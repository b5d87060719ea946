"""``python -m rlpipe [overrides]`` (also ``rlpipe`` on the PATH): ``--help`` here, before
Hydra loads; everything else is the train command, :mod:`rlpipe.command`."""

from __future__ import annotations

import sys


def main() -> None:
    """Console entry point: ``--help`` (ours; Hydra's own: ``--hydra-help``), or the command; a
    console that closes (``| head``) ends neither."""
    from rlpipe.console import console_may_close

    with console_may_close():
        if {"-h", "--help"} & set(sys.argv[1:]):
            from rlpipe.errors import RlpipeError
            from rlpipe.help import help_text

            try:
                print(help_text())
            except RlpipeError as err:  # a plug-in that does not import
                print(f"rlpipe: error: {err}", file=sys.stderr)
                sys.exit(2)
            return
        from rlpipe.command import main as command

        command()


if __name__ == "__main__":
    main()
