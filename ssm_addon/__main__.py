"""``python -m ssm_addon``: the command line (:mod:`ssm_addon.cli.command`)."""

from .cli.command import main, run

__all__ = ["main", "run"]

if __name__ == "__main__":
    run()
