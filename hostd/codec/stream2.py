"""Old import path of hostd.codec.stream.v2 (`from hostd.codec import stream2`): deprecated, goes
in the next release. This name IS that module (same object, so attributes set on one are seen
by the other); import hostd.codec.stream.v2 instead."""

import sys
import warnings

from hostd.codec.stream import v2

warnings.warn("hostd.codec.stream2 is deprecated: import hostd.codec.stream.v2", DeprecationWarning,
              stacklevel=2)
sys.modules[__name__] = v2
