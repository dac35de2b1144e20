"""Reading a TOML file with one-line errors that name the file (config, scenes, actuators)."""

from __future__ import annotations

import tomllib
from pathlib import Path

from hostd.errors import ConfigError, ConfigNotFound


def read(path: str | Path, what: str, missing_hint: str = "", exc: type[Exception] = ConfigError) -> dict:
    """The parsed document; `exc` (ConfigError by default) with the file's name otherwise."""
    p = Path(path)
    try:
        return tomllib.loads(p.read_text())
    except FileNotFoundError:
        missing = ConfigNotFound if exc is ConfigError else exc  # also the built-in FileNotFoundError
        raise missing(f"{p}: no such {what}{' (' + missing_hint + ')' if missing_hint else ''}") from None
    except PermissionError:
        raise exc(f"{p}: permission denied reading the {what}") from None
    except (OSError, UnicodeDecodeError) as e:
        raise exc(f"{p}: cannot read the {what} ({e})") from None
    except tomllib.TOMLDecodeError as e:
        raise exc(f"{p}: not valid TOML ({e})") from None
