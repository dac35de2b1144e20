"""The man page (hostd(8)) and the bash, zsh and fish completions, generated from the argparse
parser itself (hostd.parser; argparse-manpage, shtab, and fish's `complete` lines written here),
so they list exactly the commands and options `hostd` takes. `hostd manpage` and
`hostd completion SHELL` print them; `hostd install-service` installs them under /usr/local/share
(man8, bash-completion, zsh site-functions, fish vendor_completions.d)."""

from __future__ import annotations

import argparse
import re

SHELLS = ("bash", "zsh", "fish")
# where install-service puts them (relative to the prefix); searched by man, bash-completion, zsh, fish
MAN_DEST = "usr/local/share/man/man8/hostd.8"
COMPLETION_DEST = {"bash": "usr/local/share/bash-completion/completions/hostd",
                   "zsh": "usr/local/share/zsh/site-functions/_hostd",
                   "fish": "usr/local/share/fish/vendor_completions.d/hostd.fish"}

# Which arguments name a file or a directory: completed as such in every shell. An argument
# counts as a file when its dest or metavar is below (a new command gets file completion by
# naming its argument so, e.g. metavar="FILE"); everything else still falls back to file names
# in bash (-o default) but is not offered files in zsh and fish.
FILE_DESTS = frozenset({"profile", "stream", "first", "output", "thresholds", "scores", "file", "config",
                        "socket", "db", "exec_path", "scene", "input", "inputs", "profiles", "source",
                        "store", "design", "sweep", "parquet"})
FILE_METAVARS = frozenset({"FILE", "PATH", "CSV", "JSON", "STREAM", "PROFILE"})  # and FILE.png, FILE.toml ...
DIR_DESTS = frozenset({"out", "peers", "prefix", "out_dir"})
DIR_METAVARS = frozenset({"DIR"})


def path_kind(action: argparse.Action) -> str | None:
    """'file', 'dir' or None for one argument of the parser. The metavar, when it names one,
    decides before the dest (`corpus run -o FILE.sqlite` is a file though its dest is out)."""
    if action.nargs == 0 or action.choices:
        return None
    meta = action.metavar if isinstance(action.metavar, str) else None
    if meta in DIR_METAVARS:
        return "dir"
    if meta in FILE_METAVARS or (meta or "").startswith("FILE."):
        return "file"
    if action.dest in DIR_DESTS:
        return "dir"
    if action.dest in FILE_DESTS:
        return "file"
    return None


def walk(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()):
    """(command path, parser) of the parser and every subcommand, depth first."""
    yield path, parser
    for a in parser._actions:
        if isinstance(a, argparse._SubParsersAction):
            for name, sub in a.choices.items():
                yield from walk(sub, (*path, name))


def _parser(ap: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The parser (hostd.parser.build_parser's, passed in: this module generates from it and
    does not import it) with every path argument marked for shtab (`.complete`)."""
    import shtab

    for _path, p in walk(ap):
        for a in p._actions:
            kind = path_kind(a)
            if kind:
                a.complete = shtab.FILE if kind == "file" else shtab.DIRECTORY
    return ap


# ---------------------------------------------------------------- man page

_REQUEST = re.compile(r"^[.'](TH|SH|SS|B|I|BR|BI|IR|IB|RB|RI|TP|PP|P|LP|IP|HP|RS|RE|br|sp|nf|fi|ad|na|"
                      r"UR|UE|MT|ME|EX|EE|in|ti|ft|ne|\\\")(\s|$)")

EXTRA_SECTIONS = r""".SH EXIT STATUS
.TP
.B 0
success
.TP
.B 1
a check failed (\fBhostd doctor\fR found problems) or the daemon's real-time pump exited
.TP
.B 2
a usage error, or input hostd refuses (a malformed stream, profile, threshold curve or config
file, a wrong option value): the one-line message on standard error says what to change
.TP
.B 3
the display cannot be reached (not found, no permission, another protocol version, unplugged)
.TP
.B 130
interrupted (Ctrl-C)
.SH ENVIRONMENT
.TP
.B HOSTD_CONFIG
the daemon's configuration file when \fB\-\-config\fR is not given (before /etc/hostd/hostd.toml)
.TP
.B HOSTD_SOCKET
the control socket of \fBsend\fR, \fBlist\fR, \fBselect\fR, \fBstatus\fR, \fBstop\fR
(instead of the config's \fB[control] socket\fR)
.TP
.B HOSTD_CONFIG_DIR
a directory whose thresholds/ and actuators/ are searched before the shipped ones
.TP
.B HOSTD_PURE_PYTHON
set to 1: use the Python implementations instead of the compiled modules
.SH FILES
.TP
.I /etc/hostd/hostd.toml
the daemon's configuration (every key optional; \fBhostd doctor\fR checks it)
.TP
.I /run/hostd/hostd.sock
the control socket (group \fBhostd\fR, mode 0660): textures are sent, listed and selected here
.TP
.I /var/lib/hostd/library
accepted streams
.TP
.I /var/spool/hostd
drop .vtx files here to have them taken in
.TP
.I /var/lib/hostd/quality.sqlite
the quality log (\fBhostd quality\fR reads it)
.TP
.I /etc/systemd/system/hostd.service
the unit \fBhostd install\-service\fR installs (stop the service with \fBsystemctl stop hostd\fR)
.TP
.I /etc/udev/rules.d/70\-hostd.rules
gives group \fBhostd\fR the display's device nodes and names them /dev/hostd/by\-serial/hid\-SERIAL
and /dev/hostd/by\-serial/tty\-SERIAL, one per display (\fB[device] serial\fR picks one of several)
.SH SEE ALSO
.BR systemctl (1),
.BR systemd.unit (5),
.BR systemd.service (5),
.BR udev (7),
.BR udevadm (8),
.BR journalctl (1);
every command's \fB\-\-help\fR, with examples
"""


def man_page(ap: argparse.ArgumentParser) -> str:
    """hostd(8) in roff: argparse-manpage's page, made safe for groff (text lines that begin with
    '.' or \"'\" are escaped, a section name on the line after its .SH is joined to it), with
    EXIT STATUS, ENVIRONMENT, FILES and SEE ALSO sections."""
    from argparse_manpage.manpage import Manpage

    from hostd import __version__

    text = str(Manpage(ap, _data={
        "manual_section": "8", "manual_title": "hostd manual", "version": __version__,
        "project_name": "hostd",
        "description": "vibrotactile texture display daemon, codec and quality index (Iobj)"}))
    return fix_roff(text).rstrip("\n") + "\n" + _examples_section() + EXTRA_SECTIONS


def _examples_section() -> str:
    from hostd.helptext import EXAMPLES

    body = [("\\&" + ln if ln[:1] in (".", "'") else ln).replace("\\", "\\e").replace("\\e&", "\\&")
            .replace("-", "\\-") for ln in EXAMPLES.splitlines()]
    return ".SH EXAMPLES\n.nf\n" + "\n".join(body) + "\n.fi\n"


def fix_roff(text: str) -> str:
    out: list[str] = []
    lines = text.split("\n")
    i = 0
    while i < len(lines):
        line = lines[i]
        if line.strip() in (".SH", ".SS") and i + 1 < len(lines) and lines[i + 1].strip():
            out.append(f"{line.strip()} {lines[i + 1].strip()}")
            i += 2
            continue
        if line[:1] in (".", "'") and not _REQUEST.match(line):
            line = "\\&" + line  # text, not a request: '.vtx stream' would be the macro 'vtx'
        out.append(line)
        i += 1
    return "\n".join(out)


# ---------------------------------------------------------------- completions


def completion(shell: str, ap: argparse.ArgumentParser) -> str:
    if shell == "fish":
        return fish_completion(_parser(ap))
    import shtab

    text = shtab.complete(_parser(ap), shell)
    if shell == "bash":  # an argument without its own completion falls back to file names
        text, n = re.subn(r"^complete -o bashdefault -F", "complete -o bashdefault -o default -F",
                          text, flags=re.M)
        if n != 1:
            raise RuntimeError("shtab's bash script changed: cannot add -o default")
    return text


def _fish_quote(s: str) -> str:
    return "'" + s.replace("\\", "\\\\").replace("'", "\\'") + "'"


def _fish_help(s: str | None) -> str:
    s = " ".join((s or "").split())
    if s == argparse.SUPPRESS:
        return ""
    s = s.replace("%(default)s", "").replace("%%", "%")
    return s if len(s) <= 80 else s[:77] + "..."


FISH_PREAMBLE = """\
# fish completion for hostd, generated from its parser (hostd completion fish)
# __hostd_words: the words typed after `hostd` that are not options (the command path first)
function __hostd_words
    for t in (commandline -opc)[2..-1]
        string match -q -- '-*' $t; or echo $t
    end
end
# __hostd_at A B: the command path is exactly A B so far (nothing typed after it)
function __hostd_at
    set -l w (__hostd_words)
    test "$w" = "$argv"
end
# __hostd_in A B: the command path starts with A B
function __hostd_in
    set -l w (__hostd_words)
    set -l n (count $argv)
    test (count $w) -ge $n; and test "$w[1..$n]" = "$argv"
end
complete -c hostd -f
"""


def fish_completion(ap: argparse.ArgumentParser) -> str:
    lines = [FISH_PREAMBLE]
    for path, p in walk(ap):
        words = " ".join(path)
        at = _fish_quote(f"__hostd_at {words}".strip())
        inside = _fish_quote(f"__hostd_in {words}".strip())
        groups = [a for a in p._actions if isinstance(a, argparse._SubParsersAction)]
        for g in groups:
            helps = {c.dest: c.help for c in g._choices_actions}
            for name in g.choices:
                lines.append(f"complete -c hostd -n {at} -a {_fish_quote(name)} "
                             f"-d {_fish_quote(_fish_help(helps.get(name)))}")
        leaf_cond = at if groups else inside
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                continue
            kind = path_kind(a)
            desc = _fish_help(a.help)
            d = f" -d {_fish_quote(desc)}" if desc else ""
            if not a.option_strings:  # a positional
                if groups or (a.help == argparse.SUPPRESS and kind is None):
                    continue
                if kind == "file":
                    lines.append(f"complete -c hostd -n {inside} -F{d}")
                elif kind == "dir":
                    lines.append(f"complete -c hostd -n {inside} -x -a '(__fish_complete_directories)'{d}")
                elif a.choices:
                    lines.append(f"complete -c hostd -n {inside} -x -a "
                                 f"{_fish_quote(' '.join(map(str, a.choices)))}{d}")
                continue
            opts = ""
            for o in a.option_strings:
                if o.startswith("--"):
                    opts += f" -l {o[2:]}"
                elif len(o) == 2:
                    opts += f" -s {o[1]}"
                else:
                    opts += f" -o {o[1:]}"
            if a.nargs == 0:
                value = ""
            elif a.choices:
                value = f" -x -a {_fish_quote(' '.join(map(str, a.choices)))}"
            elif kind == "file":
                value = " -r -F"
            elif kind == "dir":
                value = " -x -a '(__fish_complete_directories)'"
            else:
                value = " -x"
            lines.append(f"complete -c hostd -n {leaf_cond}{opts}{value}{d}")
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------- the CLI reference (Markdown)


def _md_escape(text: str) -> str:
    return (text or "").replace("|", "\\|").replace("<", "&lt;").replace(">", "&gt;").replace("%%", "%")


def cli_markdown(ap: argparse.ArgumentParser) -> str:
    """The command-line reference of the docs site (its reference/cli.md), from the same parser
    as the man page: every command, its usage, arguments and options with their help and
    defaults. Hidden options (old spellings kept for a release) are left out."""
    out = ["# Command-line reference", "",
           "Every `hostd` command with its arguments and options, generated from the parser that "
           "parses them (the same source as `hostd manpage`; `hostd manpage --markdown` prints this page). "
           "Each command also prints its part with `--help`.", ""]
    for path, p in walk(ap):
        if not path:
            continue
        subs = [a for a in p._actions if isinstance(a, argparse._SubParsersAction)]
        name = "hostd " + " ".join(path)
        depth = min(len(path) + 1, 4)
        out += ["#" * depth + f" `{name}`", ""]
        desc = p.description or _help_of(ap, path)
        if desc:
            out += [_md_escape(" ".join(desc.split())), ""]
        usage = " ".join(p.format_usage().split())
        out += ["```text", usage.replace("usage: ", "", 1), "```", ""]
        if subs:
            continue
        rows = []
        for a in p._actions:
            if a.help == argparse.SUPPRESS or isinstance(a, argparse._HelpAction):
                continue
            spell = ", ".join(f"`{o}`" for o in a.option_strings) or f"`{a.metavar or a.dest}`"
            help_ = _md_escape(" ".join((a.help or "").split()))
            if a.choices and not isinstance(a, argparse._SubParsersAction):
                help_ += f" (one of {', '.join(f'`{c}`' for c in a.choices)})"
            if a.option_strings and a.nargs != 0 and a.default not in (None, argparse.SUPPRESS, [], False) \
                    and "default" not in help_:
                help_ += f" (default `{a.default}`)"
            rows.append(f"| {spell} | {help_} |")
        if rows:
            out += ["| argument | what it does |", "|---|---|", *rows, ""]
    return "\n".join(out)


def _help_of(ap: argparse.ArgumentParser, path: tuple[str, ...]) -> str:
    """The one-line help its parent gave the command `path`."""
    parent = ap
    for name in path[:-1]:
        parent = next(a for a in parent._actions if isinstance(a, argparse._SubParsersAction)).choices[name]
    for a in parent._actions:
        if isinstance(a, argparse._SubParsersAction):
            for choice in a._choices_actions:
                if choice.dest == path[-1]:
                    return choice.help or ""
    return ""
