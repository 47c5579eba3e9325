"""`python -m app link-decode FILE --protocol P`: the frames of a --link-capture file (docs/serial-protocol.md)."""
from __future__ import annotations

from app.cli import UserError
from vehicles.link_capture import CaptureError, decode_capture, read_capture
from vehicles.link_protocols import HARDWARE_DEFAULT, PROTOCOLS, UnknownProtocolError, check_protocol


def register(sub) -> None:
    p = sub.add_parser("link-decode", help="print the frames of a serial link capture (race --link-capture) "
                                           "and count the bad ones")
    p.add_argument("capture", metavar="FILE", help="capture file written by race --link-capture")
    p.add_argument("--protocol", default=HARDWARE_DEFAULT, metavar="|".join(PROTOCOLS),
                   help=f"frame format of the tx bytes (default {HARDWARE_DEFAULT})")
    p.add_argument("--quiet", action="store_true", help="print only the summary and the last frame")
    p.set_defaults(func=run)


def _values(frame, protocol: str) -> str:
    if protocol == "buzzracer-fhss":
        return "  ".join(f"m{m} {s}/{t}" for m, (s, t) in sorted(frame.cars.items()))
    return f"seq {frame.seq:5d}  " + "  ".join(f"car {c} steer {s:+.4f} thr {t:+.4f}" for c, (s, t) in sorted(frame.cars.items()))


def run(args) -> int:
    try:
        check_protocol(args.protocol, "--protocol")
        report = decode_capture(read_capture(args.capture), args.protocol)
    except (CaptureError, UnknownProtocolError) as exc:
        raise UserError(str(exc)) from None
    unit = "steering/throttle pulse us per modem id" if args.protocol == "buzzracer-fhss" else "normalised values"
    print(f"{args.capture}: {args.protocol}, {report.tx_bytes} bytes sent, {report.rx_bytes} received; "
          f"frames ({unit}), all with a good CRC:")
    shown = report.frames[-1:] if args.quiet else report.frames
    for frame in shown:
        print(f"{frame.t:12.6f}  {_values(frame, args.protocol)}  crc ok")
    for t, offset in report.bad_at:
        print(f"{t:12.6f}  BAD frame starting at tx byte offset {offset}")
    for t, line in ([] if args.quiet else report.box_text):
        print(f"{t:12.6f}  box: {line}")
    bad = ", ".join(f"{k} {v}" for k, v in report.bad.items() if v)
    print(f"{len(report.frames)} good frames, {report.bad_frames} bad" + (f" ({bad})" if bad else "")
          + f"; {len(report.box_text)} lines of box text")
    return 1 if report.bad_frames else 0
