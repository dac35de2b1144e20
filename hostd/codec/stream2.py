"""Old import path of hostd.codec.stream.v2 (`from hostd.codec import stream2`), kept so that
code written against it still works: this name IS that module (same object, so attributes set
on one are seen by the other)."""

import sys

from hostd.codec.stream import v2

sys.modules[__name__] = v2
