"""Generate firmware/include/hostd_proto.h from protocol.toml: python -m hostd.device.gen_header [OUT]
(the cycle's state header, hostd/device/cycle_state.h, is generated at build: hostd.cyclestate)"""

from __future__ import annotations

import sys
from pathlib import Path

from hostd.device import protocol as pr

_ROOT = Path(__file__).resolve().parents[2]
HEADER = _ROOT / "firmware" / "include" / "hostd_proto.h"
_SIZES = {"B": 1, "H": 2, "I": 4, "h": 2, "i": 4, "f": 4}
_KIND = {"h": 1, "i": 1, "f": 2}  # X macro's 4th argument: 0 unsigned, 1 signed, 2 float32


def render() -> str:
    lines = ["/* GENERATED from hostd/device/protocol.toml by `python -m hostd.device.gen_header`.",
             " * Do not edit: change the TOML and regenerate (a test checks this file is current). */",
             "#ifndef HOSTD_PROTO_H", "#define HOSTD_PROTO_H", ""]
    for k, v in pr.P.items():
        if isinstance(v, list):
            for i, part in zip(("MAJOR", "MINOR", "PATCH"), v, strict=True):
                lines.append(f"#define HP_{k.upper()}_{i} {part}")
        else:
            val = f"{v:#x}" if k.startswith("usb") else str(v)
            lines.append(f"#define HP_{k.upper()} {val}")
    lines.append("")
    for k, v in pr.R.items():
        lines.append(f"#define HP_RENDER_{k.upper()} {v}")
    lines.append("")
    for group, prefix in (("ids", "HP_ID_"), ("states", "HP_STATE_"), ("faults", "HP_FAULT_"),
                          ("render_states", "HP_RSTATE_"), ("results", "HP_RESULT_")):
        for k, v in pr.SPEC[group].items():
            lines.append(f"#define {prefix}{k} 0x{v:02x}")
        lines.append("")
    for name, lay in pr.LAYOUTS.items():
        off = 0
        for fname, code in lay.fields:
            lines.append(f"#define HP_{name}_OFF_{fname.upper()} {off}")
            off += _SIZES[code]
        lines.append(f"#define HP_{name}_SIZE {off}")
        if lay.variable:
            lines.append(f"#define HP_{name}_MAX_{lay.var_name.upper()} {lay.var_max}")
        xs = []
        off = 0
        for fname, code in lay.fields:
            xs.append(f"X({fname}, {off}, {_SIZES[code]}, {_KIND.get(code, 0)})")
            off += _SIZES[code]
        lines.append("/* X(name, offset, size, kind) per fixed field; kind 0 unsigned, 1 signed, 2 f32 */")
        lines.append(f"#define HP_{name}_FIELDS(X) " + " ".join(xs))
        lines.append("")
    lines.append("#endif")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv:
        out = Path(argv[0])
    elif (_ROOT / "firmware" / "Makefile").is_file() and (_ROOT / "pyproject.toml").is_file():
        out = HEADER  # a source checkout: regenerate the firmware's header in place
    else:  # an installed package: never write into site-packages
        print("gen_header: no source tree here (hostd is installed as a package): give the output "
              "file, e.g. python -m hostd.device.gen_header firmware/include/hostd_proto.h", file=sys.stderr)
        return 2
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(render())
    print(out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
