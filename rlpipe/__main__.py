"""``python -m rlpipe [overrides]`` (also ``rlpipe`` on the PATH): ``--help`` here, before
Hydra loads; everything else is the train command, :mod:`rlpipe.command`."""

from __future__ import annotations

import os
import sys


def main() -> None:
    """Console entry point: ``--help`` (ours; Hydra's own: ``--hydra-help``), or the command."""
    if {"-h", "--help"} & set(sys.argv[1:]):
        from rlpipe.errors import RlpipeError
        from rlpipe.help import help_text

        try:
            print(help_text(), flush=True)
        except RlpipeError as err:  # a plug-in that does not import
            print(f"rlpipe: error: {err}", file=sys.stderr)
            sys.exit(2)
        except BrokenPipeError:  # `--help | head`: the reader left early, as with any Unix tool
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # none at exit
            sys.exit(141)  # 128 + SIGPIPE, what a shell reports for a tool a closed pipe stopped
        return
    from rlpipe.command import main as command

    command()


if __name__ == "__main__":
    main()
