"""The optional compiled modules; everything else is in pyproject.toml.

optional=True: without a C compiler the build goes on and hostd uses the pure-Python code,
which is the reference each compiled module is tested against (same bytes, same samples, slower):
  hostd/codec/_rangecoder.c   the stream-v2 index coder (reference: hostd/codec/rangecoder.py)
  hostd/device/_fastlink.c    the link's per-message decode/encode (reference: hostd/device/protocol.py)
  hostd/render/_fastrender.c  equalizer + output stage + codes of a real-time batch, and the
                              batch's series (reference: hostd/render/equalizer.py, output.py,
                              series.clenshaw_py; the arithmetic is in render_core.h)
  hostd/device/_fastpump.c    the host-rendering pump's steady-state cycle (reference:
                              hostd/device/pump.py Pump.step / Pump.run)
-ffp-contract=off: no fused multiply-add, so the compiled renderer rounds exactly as Python does.
hostd/device/cycle_state.h, the structs of the cycle's state records, is generated here from
hostd/device/cycle_state.toml (hostd/cyclestate.py, stdlib only), so it is never out of date.
"""

import runpy

from setuptools import Extension, setup

runpy.run_path("hostd/cyclestate.py")["write_header"]()  # hostd/device/cycle_state.h
# the serial framing is the firmware's (one C implementation), with the protocol header it includes
FRAMING = ["firmware/src/framing.c"]
FW = {"include_dirs": ["firmware/include"],
      "depends": ["firmware/include/fw_framing.h", "firmware/include/hostd_proto.h",
                  "hostd/device/cycle_state.toml", "hostd/device/protocol.toml",
                  "hostd/render/render_core.h"]}

setup(ext_modules=[
    Extension("hostd.codec._rangecoder", ["hostd/codec/_rangecoder.c"], optional=True),
    Extension("hostd.device._fastlink", ["hostd/device/_fastlink.c", *FRAMING], optional=True, **FW),
    Extension("hostd.render._fastrender", ["hostd/render/_fastrender.c"], optional=True,
              depends=["hostd/render/render_core.h", "hostd/device/cycle_state.toml"],
              extra_compile_args=["-ffp-contract=off"]),
    Extension("hostd.device._fastpump", ["hostd/device/_fastpump.c", *FRAMING], optional=True,
              extra_compile_args=["-ffp-contract=off"], **FW),
])
