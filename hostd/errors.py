"""Error types whose message is one line that tells the user what to do.

Each is also the built-in exception a Python caller already catches: bad input or arguments are
ValueError (StreamError, ProfileError, ThresholdError, ConfigError, CodecError, FitError,
QualityError), a file that does not exist is FileNotFoundError (ProfileNotFound, StreamNotFound,
ThresholdNotFound, ConfigNotFound, ScoresNotFound), so `api.load_profile('/nonexistent')` raises
what `open()` would.
`hostd.api` warns with HostdWarning (a UserWarning) where the CLI prints a note.
"""


class HostdError(Exception):
    """Base of every error a user can cause; the CLI prints it as one line, exit code 2."""

    exit_code = 2


class HostdWarning(UserWarning):
    """What `hostd.api` says where the CLI prints a note or a warning (filter it with the warnings
    module: warnings.simplefilter("ignore", HostdWarning))."""


class StreamError(HostdError, ValueError):
    """A .vtx stream is malformed, truncated, corrupt or of an unsupported version."""


class ProfileError(HostdError, ValueError):
    """A height profile could not be loaded or is unusable."""


class ThresholdError(HostdError, ValueError):
    """A detection-threshold curve is malformed."""


class ProfileNotFound(ProfileError, FileNotFoundError):
    """The profile file does not exist."""


class ThresholdNotFound(ThresholdError, FileNotFoundError):
    """The threshold-curve file does not exist."""


class ConfigError(HostdError, ValueError):
    """A configuration file or parameter is invalid."""


class ConfigNotFound(ConfigError, FileNotFoundError):
    """A config, scene or other TOML file that does not exist."""


class StreamNotFound(StreamError, FileNotFoundError):
    """The .vtx stream file does not exist."""


class CodecError(HostdError, ValueError):
    """Codec parameters are invalid (levels, b0, geometry)."""


class FitError(HostdError, ValueError):
    """Subjective-score data cannot be fitted (degenerate or malformed)."""


class ScoresNotFound(FitError, FileNotFoundError):
    """The scores CSV does not exist."""


class QualityError(HostdError, ValueError):
    """Non-finite or mismatched input to the quality indices."""


class DeviceError(HostdError):
    """The display cannot be reached or does not speak our protocol. exit code 3."""

    exit_code = 3


class DeviceNotFound(DeviceError):
    """No display matched (the message lists what was seen)."""


class DevicePermission(DeviceError):
    """The display exists but this user may not open it (the message names the udev rule)."""


class DeviceVersion(DeviceError):
    """The display speaks another protocol version or has incompatible parameters."""


class DeviceGone(DeviceError):
    """The display went away mid-stream (unplugged)."""


class DeviceBusy(DeviceError):
    """A transient I/O condition (write timeout, EAGAIN): retried, never a reason to drop
    the device; only a vanished device (ENODEV, EIO, hang-up) is DeviceGone."""


class DeviceTimeout(DeviceError):
    """The device did not answer a request in time: it may be slow (an emulated or starved
    host), which is not a refusal; the caller may ask once more."""


class ExperimentError(HostdError, ValueError):
    """An experiment's design, session or stimulus is unusable (unknown texture, reused token,
    a stimulus beyond the display's reach)."""


class StimulusRefused(ExperimentError):
    """A stimulus beyond the display's reach, or not a finite one: refused before anything is
    played (by the host, and by the daemon for its clients)."""
