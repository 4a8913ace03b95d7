"""What every help screen shares: ``-h`` beside ``--help``, an example at the end, and
flags shown as flags.

Every typer app and sub-app is made with ``context_settings=CONTEXT``; every command
and group gets ``epilog=example(...)``, one working command line that
``tests/test_cli_help.py`` finds at the end of its help (and runs, for the cheap ones).
"""

from __future__ import annotations

__all__ = ["CONTEXT", "example"]

#: context settings of every app and sub-app: ``-h`` is ``--help``
CONTEXT = {"help_option_names": ["-h", "--help"]}

#: how a help screen's last line starts
EXAMPLE = "Example: "


def example(command: str) -> str:
    """The epilog of a help screen: one command line that works from a checkout's root."""
    if not command.startswith("fringecal "):
        raise ValueError(f"an example is a fringecal command line, not {command!r}")
    return EXAMPLE + command


def _flags_without_a_type() -> None:
    """Show ``--json``, not ``--json <bool>``, in the rich help of typer 0.29.

    typer 0.29.0 replaced the metavar of its rich option table by
    ``TyperOption.display_type_rich``, which returns the annotation's type for every
    option, flags included (its own ``--help`` reads ``--help <bool>``); typer 0.28 and
    its plain help (``get_help_record``) leave a flag without one, since a flag takes no
    value. Restores that for flags and counters; a typer without the method is left as
    it is.
    """
    from typer.core import TyperOption

    shown = getattr(TyperOption, "display_type_rich", None)
    if shown is None or getattr(shown, "flags_bare", False):
        return

    def display_type_rich(self, ctx):
        return None if self.is_flag or self.count else shown(self, ctx)

    display_type_rich.flags_bare = True
    TyperOption.display_type_rich = display_type_rich


_flags_without_a_type()
