"""The demo on the embedded default: what the README's first command runs."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from hostd.codec import stream as vtx
from hostd.codec import transform
from hostd.perception import indices, thresholds
from hostd.quality import score_stream
from hostd.texture import synth

DEMO_SETTINGS = (
    {"method": "quant", "levels": 14},
    {"method": "quant", "levels": 8},
    {"method": "quant", "levels": 4},
    {"method": "cut", "b0_db": -4.0, "value_bits": 16},
    {"method": "cut", "b0_db": 4.0, "value_bits": 16},
)


def _in_dir(out_dir: str | None, body) -> int:
    """Run body(out) in out_dir, or in a temporary directory that is removed once the demo has
    succeeded (a failed one keeps it, with the daemon's log, and says where)."""
    import shutil

    if out_dir:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        return body(out)
    out = Path(tempfile.mkdtemp(prefix="hostd-demo-"))
    ok = False
    try:
        rc = body(out)
        ok = rc == 0
        return rc
    finally:
        if ok:
            shutil.rmtree(out, ignore_errors=True)
            print(f"  removed {out} (-o DIR keeps the demo's files)")
        else:
            import sys

            print(f"hostd demo: kept {out} for its logs", file=sys.stderr)


def codec_demo(out_dir: str | None = None) -> int:
    """Encode synthetic wood and sandpaper at several levels; print bytes and quality."""
    return _in_dir(out_dir, _codec_demo)


def _codec_demo(out: Path) -> int:
    curve = thresholds.default_curve()
    print(f"{'texture':<10} {'setting':<22} {'bytes':>6} {'%coeffs':>8} {'Ip':>7} {'Ia':>7} "
          f"{'Iobj':>7}  nearest grade")
    for kind in ("wood", "sandpaper"):
        prof = synth.make(kind, seed=1)
        geom = transform.Geometry(prof.n, prof.length_mm)
        for s in DEMO_SETTINGS:
            data = vtx.v1.encode_profile(prof.heights_um, geom, curve, **s)
            tag = (f"quant L={s['levels']}" if s["method"] == "quant"
                   else f"cut b0={s['b0_db']:+.0f}dB 16-bit")
            name = f"{kind}-{tag.replace(' ', '_').replace('=', '')}.vtx"
            (out / name).write_bytes(data)
            st = vtx.decode(data)
            sc = score_stream(st)
            print(f"{kind:<10} {tag:<22} {st.nbytes:>6} {100 * st.ratio_coeffs:>7.1f}% "
                  f"{float(sc.Ip):>7.4f} {float(sc.Ia):>7.4f} {float(sc.Iobj):>7.4f}  "
                  f"{indices.grade(float(sc.Iobj))}")
    print(indices.IOBJ_LEGEND)
    print(f"streams written to {out}")
    return 0


# ------------------------------------------------------------------ the daemon demo
PLAY_SETTINGS = (
    ("q14", {"method": "quant", "levels": 14}),
    ("q4", {"method": "quant", "levels": 4}),
    ("cut0", {"method": "cut", "b0_db": 0.0, "value_bits": 16}),
)


def _firmware_host_port() -> Path | None:
    """Build the firmware's host port (make + cc); None when it cannot be built here."""
    from hostd.device import hostport

    try:
        return hostport.build()
    except RuntimeError:
        return None


def daemon_demo(out_dir: str | None = None, seconds_per_texture: float = 3.5,
                force_sim: bool = False, render_at: str = "auto") -> int:
    """The README's main job: the daemon on the embedded default device, end to end."""
    return _in_dir(out_dir, lambda out: _daemon_demo(out, seconds_per_texture, force_sim, render_at))


def _daemon_demo(out: Path, seconds_per_texture: float, force_sim: bool, render_at: str) -> int:
    import subprocess
    import sys
    import time

    from hostd.service.cli import format_status
    from hostd.service.client import request, send_file

    exe = None if force_sim else _firmware_host_port()
    fw = None
    if exe is not None:
        fw = subprocess.Popen([str(exe), "--motion", "metronome", "--log", str(out / "dac.bin"),
                               "--duration", "300"], stdout=subprocess.PIPE,
                              stderr=open(out / "firmware.log", "w"), text=True)
        transport = "serial:" + fw.stdout.readline().split()[1]
        what = f"the firmware's host port on {transport[7:]} (C core, 3 kHz, metronome hand)"
    else:
        transport = "sim"
        what = "the simulated display (the firmware's host port could not be built here)"
    sock = out / "hostd.sock"
    (out / "hostd.toml").write_text(
        f'[device]\ntransport = "{transport}"\ntarget_fill = 24\n[render]\nwhere = "{render_at}"\n'
        f'[library]\ndir = "library"\nspool = "spool"\n'
        f'[control]\nsocket = "hostd.sock"\ngroup = ""\n[quality]\ndb = "quality.sqlite"\n')
    print(f"hostd demo: daemon on {what}\n  files in {out}")
    daemon = subprocess.Popen([sys.executable, "-m", "hostd", "run", "--config", str(out / "hostd.toml")],
                              stdout=subprocess.DEVNULL, stderr=open(out / "hostd.log", "w"))
    try:
        t_end = time.monotonic() + 20
        st = {}
        while time.monotonic() < t_end:
            if daemon.poll() is not None:
                print((out / "hostd.log").read_text()[-2000:], file=sys.stderr)
                raise SystemExit("hostd demo: the daemon exited early (log above)")
            try:
                st = request(str(sock), {"cmd": "status"}, timeout_s=2)
                if st["connected"]:
                    break
            except Exception:
                pass
            time.sleep(0.2)
        if not st.get("connected"):
            raise SystemExit(f"hostd demo: the daemon did not connect to {transport} (see {out}/hostd.log)")
        curve = thresholds.default_curve()
        names = []
        for kind in ("wood", "sandpaper"):
            prof = synth.make(kind, seed=1)
            geom = transform.Geometry(prof.n, prof.length_mm)
            for tag, s in PLAY_SETTINGS:
                f = out / f"{kind}-{tag}.vtx"
                f.write_bytes(vtx.v1.encode_profile(prof.heights_um, geom, curve, **s))
                r = send_file(str(sock), str(f), None)
                names.append(r["name"])
        # and one corrupt stream, to show it is refused without disturbing anything
        bad = out / "corrupt.vtx"
        bad.write_bytes((out / "wood-q14.vtx").read_bytes()[:-5])
        try:
            send_file(str(sock), str(bad), None)
        except Exception as e:
            print(f"  refused corrupt.vtx: {e}")
        print(f"  sent {len(names)} streams; playing each for {seconds_per_texture:g} s under the "
              "paper's metronome strokes")
        from hostd.tty import on_terminal

        tty = on_terminal(sys.stdout)
        for name in names:
            request(str(sock), {"cmd": "select", "name": name})
            t_stop = time.monotonic() + seconds_per_texture
            while time.monotonic() < t_stop:
                time.sleep(0.25)
                line = format_status(request(str(sock), {"cmd": "status"}))
                if tty:
                    print("\r  " + line, end="", flush=True)
            if not tty:
                print("  " + line)
        if tty:
            print()
        request(str(sock), {"cmd": "stop"})
        time.sleep(0.2)
        st = request(str(sock), {"cmd": "status"})
        rows = request(str(sock), {"cmd": "quality"})["rows"]
        request(str(sock), {"cmd": "shutdown"})
        daemon.wait(15)
    finally:
        if daemon.poll() is None:
            daemon.terminate()
            daemon.wait(10)
        if fw is not None:
            fw.terminate()
            fw.wait(10)
    print("summary")
    if st.get("render_at") == "device":  # the display's RENDER_STATUS counters
        print(f"  the display rendered {st['device_rendered_s']:.1f} s at full gain, "
              f"{st['device_faded_s']:.2f} s fading, {st['device_idle_s']:.2f} s idle; "
              f"host lost {st['device_host_lost']}x, re-uploads "
              f"{st['device_reuploads']} (its own counters); pump wake-ups {st['wakeups']}; streams accepted "
              f"{st['accepted']}, refused {st['refused']}")
    else:
        print(f"  the device played {st['device_samples_played']} samples from its buffer, "
              f"{st['device_underruns']} underrun episode(s) (its own counters); host stalls {st['stalls']} "
              f"(longest {st['longest_stall_ms']:.0f} ms), recoveries {st['recoveries']}, deadline misses "
              f"{st['deadline_misses']}; streams accepted {st['accepted']}, refused {st['refused']}")
    if fw is not None and (out / "dac.bin").exists():
        from hostd.device import hostport

        rec = hostport.read_log(out / "dac.bin")
        rend = np.flatnonzero(rec["flags"] & hostport.RENDERING)
        if st.get("render_at") == "device" and rend.size:
            span = rec["flags"][rend[0] : rend[-1] + 1]
            print(f"  firmware DAC log: the display rendered the texture itself on "
                  f"{np.mean((span & hostport.RENDERING) != 0):.2%} of the ticks from the first rendered one "
                  f"to the last, at full gain on {np.mean((span & hostport.FULL_GAIN) != 0):.2%} "
                  f"(device mode: nothing streamed; {st['render_reason']})")
        else:
            fig = hostport.playback_figures(rec, to_last_played=True)
            print(f"  firmware DAC log: played from the buffer {fig['played_fraction']:.2%} of the ticks "
                  f"from the first sample to the last (texture switches included), "
                  f"{fig['underrun_episodes']} underrun episode(s), "
                  f"longest silence {fig['longest_silence_ms']:.0f} ms")
    print(f"  quality log ({out / 'quality.sqlite'}): {len(rows)} rows")
    print(f"  {'name':<16} {'bytes':>6} {'method':<6} {'Ip':>8} {'Ia':>8} {'Iobj':>8} {'played':>8} "
          f"{'underruns':>9}  nearest grade")
    for r in rows:  # received (Iobj) next to delivered (the device's counters while it played)
        pf = "-" if r.get("played_fraction") is None else f"{r['played_fraction']:.2%}"
        un = "-" if r.get("underruns") is None else str(r["underruns"])
        print(f"  {r['name']:<16} {r['bytes']:>6} {r['method']:<6} {r['ip']:>8.4f} {r['ia']:>8.4f} "
              f"{r['iobj']:>8.4f} {pf:>8} {un:>9}  {indices.grade(r['iobj'])}")
    print(f"  {indices.IOBJ_LEGEND}")
    return 0
