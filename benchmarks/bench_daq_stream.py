"""DAQ stream at 2 kHz x 20 (40,000 frames/s) from the simulator over a pseudo-terminal
to the rig's reader: frames received and lost, and the CPU each side uses.

Targets: no frame lost; the simulator process below one core (issue 2); the reader
below half a core (issue 3).  Baseline: the same stream read by a plain pyserial loop
that only checks the sync word and CRC frame by frame in Python (what a first
driver would do), measured on the same stream for a few seconds.

With ``--line-baud 921600``: the DAQ at the line limit of its fastest serial setting,
end to end (the simulator's device, the pseudo-terminal, the rig's reader): 921,600 Bd
8N1 carries 92,160 bytes/s, 5,760 frames of 16 bytes; the device streams at its top rate
(5 kHz) with the simulator at 5760/5000 = 1.152x, so that the frames arrive at exactly
the line's capacity (a pseudo-terminal has no baud rate of its own: the device paces
them).  Target: 0 frames lost, every frame's sequence number in order.

    python benchmarks/bench_daq_stream.py [--seconds 60]
    python benchmarks/bench_daq_stream.py --line-baud 921600 [--seconds 60]
"""

from __future__ import annotations

import argparse
import os
import struct
import subprocess
import sys
import time

import crcmod.predefined

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from rig.drivers.daq import Daq  # noqa: E402

TICKS = os.sysconf("SC_CLK_TCK")


def cpu_seconds(pid: int) -> float:
    fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICKS


def start_simulator(speed: float) -> tuple[subprocess.Popen, str]:
    proc = subprocess.Popen([sys.executable, "-m", "simulator", "serve", "--modbus", "tcp://127.0.0.1:0",
                             "--daq", "pty", "--speed", str(speed)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout is not None  # a pipe: stdout=PIPE
    urls = {}
    for _ in range(2):
        kind, url = proc.stdout.readline().split()
        urls[kind] = url
    return proc, urls["daq"]


FRAME_BYTES = 16
BITS_PER_CHAR = 10                 # 8N1: start, 8 data, stop
DAQ_MAX_RATE_HZ = 5000             # the DAQ's top sample rate (RATE 100..5000)


def rig_reader(url: str, seconds: float, rate_hz: int = 2000) -> dict[str, float]:
    daq = Daq(url, rate_hz=rate_hz)
    daq.open()
    c0, w0 = time.process_time(), time.monotonic()
    daq.start()
    time.sleep(seconds)
    issued = daq.stop()
    cpu, wall = time.process_time() - c0, time.monotonic() - w0
    out = {"received": daq.parser.received, "issued": issued, "lost": daq.counters.lost_samples,
           "crc": daq.counters.crc_errors, "frames_per_s": daq.parser.received / wall, "cpu": cpu / wall}
    daq.close()
    return out


def naive_reader(url: str, seconds: float) -> dict[str, float]:
    import serial

    crc = crcmod.predefined.mkCrcFun("modbus")
    port = serial.Serial(url, timeout=0.05)
    port.write(b"STOP\n")
    time.sleep(0.3)
    port.reset_input_buffer()
    port.write(b"RATE 2000\nSTART\n")
    port.readline(), port.readline()
    buf, frames, last, lost = b"", 0, None, 0
    c0, w0 = time.process_time(), time.monotonic()
    while time.monotonic() - w0 < seconds:
        buf += port.read(65536)
        i = 0
        while i + 16 <= len(buf):
            if (buf[i] != 0xA5 or buf[i + 1] != 0x5A
                    or crc(buf[i + 2:i + 14]) != struct.unpack_from("<H", buf, i + 14)[0]):
                i += 1
                continue
            seq = struct.unpack_from("<H", buf, i + 2)[0]
            if last is not None:
                lost += (seq - last - 1) & 0xFFFF
            last, frames, i = seq, frames + 1, i + 16
        buf = buf[i:]
    cpu, wall = time.process_time() - c0, time.monotonic() - w0
    port.write(b"STOP\n")
    port.close()
    return {"received": frames, "lost": lost, "frames_per_s": frames / wall, "cpu": cpu / wall}


def at_line_limit(baud: float, seconds: float) -> int:
    frames_per_s = baud / BITS_PER_CHAR / FRAME_BYTES
    speed = frames_per_s / DAQ_MAX_RATE_HZ
    proc, url = start_simulator(speed)
    try:
        s0, w0 = cpu_seconds(proc.pid), time.monotonic()
        rig = rig_reader(url, seconds, DAQ_MAX_RATE_HZ)
        sim_cpu = (cpu_seconds(proc.pid) - s0) / (time.monotonic() - w0)
    finally:
        proc.terminate()
        proc.wait(timeout=20)
    print(f"DAQ at the line limit of {baud:g} Bd 8N1: {baud / BITS_PER_CHAR:.0f} bytes/s = {frames_per_s:.0f} "
          f"frames/s of {FRAME_BYTES} bytes; the device at {DAQ_MAX_RATE_HZ} Hz x {speed:.3f} over a pty, "
          f"{seconds:g} s wall")
    print(f"  frames issued {rig['issued']}, received {rig['received']}, lost {rig['lost']}, CRC errors "
          f"{rig['crc']}; {rig['frames_per_s']:.0f} frames/s = {rig['frames_per_s'] / frames_per_s:.1%} of the line")
    print(f"  reader CPU {rig['cpu']:.0%} of a core, simulator {sim_cpu:.0%}")
    met = rig["lost"] == 0 and rig["crc"] == 0 and rig["received"] >= rig["issued"] > 0
    print(f"target: 0 frames lost end to end at the line's limit -> {'met' if met else 'NOT met'}")
    return 0 if met else 1


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=60.0, help="wall seconds of streaming (default 60)")
    parser.add_argument("--baseline-seconds", type=float, default=5.0)
    parser.add_argument("--line-baud", type=float, help="stream at this serial line's limit (e.g. 921600)")
    args = parser.parse_args()
    if args.line_baud:
        return at_line_limit(args.line_baud, args.seconds)

    proc, url = start_simulator(20.0)
    try:
        s0, w0 = cpu_seconds(proc.pid), time.monotonic()
        rig = rig_reader(url, args.seconds)
        sim_cpu = (cpu_seconds(proc.pid) - s0) / (time.monotonic() - w0)
        naive = naive_reader(url, args.baseline_seconds)
    finally:
        proc.terminate()
        proc.wait(timeout=20)
    print(f"DAQ stream, 2 kHz x 20 over a pty, {args.seconds:g} s wall ({args.seconds * 20:g} s simulated)")
    print(f"{'reader':<34} {'frames/s':>10} {'received':>10} {'lost':>6} {'reader CPU':>11}")
    print(f"{'rig.drivers.daq (vectorised parser)':<34} {rig['frames_per_s']:>10.0f} {rig['received']:>10} "
          f"{rig['lost']:>6} {rig['cpu']:>10.0%}")
    print(f"{'baseline: per-frame Python loop':<34} {naive['frames_per_s']:>10.0f} {naive['received']:>10} "
          f"{naive['lost']:>6} {naive['cpu']:>10.0%}")
    print(f"simulator process CPU while serving: {sim_cpu:.0%} of one core (target < 100 %)")
    met = rig["lost"] == 0 and rig["frames_per_s"] > 39000 and rig["cpu"] < 0.5 and sim_cpu < 1
    print(f"targets: 40000 frames/s, 0 lost, reader < 50 % of a core -> {'met' if met else 'NOT met'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
