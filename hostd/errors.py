"""Error types whose message is one line that tells the user what to do."""


class HostdError(Exception):
    """Base of every error a user can cause; the CLI prints it as one line, exit code 2."""

    exit_code = 2


class StreamError(HostdError):
    """A .vtx stream is malformed, truncated, corrupt or of an unsupported version."""


class ProfileError(HostdError):
    """A height profile could not be loaded or is unusable."""


class ThresholdError(HostdError):
    """A detection-threshold curve is malformed."""


class ConfigError(HostdError):
    """A configuration file or parameter is invalid."""


class CodecError(HostdError):
    """Codec parameters are invalid (levels, b0, geometry)."""


class FitError(HostdError):
    """Subjective-score data cannot be fitted (degenerate or malformed)."""


class QualityError(HostdError):
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


class ExperimentError(HostdError):
    """An experiment's design, session or stimulus is unusable (unknown texture, reused token,
    a stimulus beyond the display's reach)."""
