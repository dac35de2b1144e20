"""The man page (hostd(8)) and the bash and zsh completions, generated from the argparse parser
itself (argparse-manpage, shtab), so they list exactly the commands and options `hostd` takes.
`hostd manpage` and `hostd completion SHELL` print them; `hostd install-service` installs them
under /usr/local/share (man8, bash-completion, zsh site-functions)."""

from __future__ import annotations

SHELLS = ("bash", "zsh")
# where install-service puts them (relative to the prefix); searched by man, bash-completion, zsh
MAN_DEST = "usr/local/share/man/man8/hostd.8"
COMPLETION_DEST = {"bash": "usr/local/share/bash-completion/completions/hostd",
                   "zsh": "usr/local/share/zsh/site-functions/_hostd"}


def man_page() -> str:
    from argparse_manpage.manpage import Manpage

    from hostd import __version__
    from hostd.parser import build_parser

    return str(Manpage(build_parser(), _data={
        "manual_section": "8", "manual_title": "hostd manual", "version": __version__,
        "project_name": "hostd",
        "description": "vibrotactile texture display daemon, codec and quality index (Iobj)"}))


def completion(shell: str) -> str:
    import shtab

    from hostd.parser import build_parser

    return shtab.complete(build_parser(), shell)
