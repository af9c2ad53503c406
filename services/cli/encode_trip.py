"""`csr encode-trip IN OUT [--keyframe-spacing-m M] [--point-decimals D] [--gzip]`: convert a
JSON trip upload (plain or ``.gz``) into the compact binary upload
(``application/vnd.csr.trip+cbor``, docs/upload-binary.md), and `csr decode-trip IN OUT` back
into JSON. The input is validated like an upload first; the size of each form is printed."""

from __future__ import annotations

import argparse
import gzip
import sys
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("encode-trip", help="convert a JSON trip upload into the compact binary upload")
    p.add_argument("input", type=Path, help="the JSON upload (.json or .json.gz)")
    p.add_argument("output", type=Path, help="the binary upload to write (.cbor, or .cbor.gz with --gzip)")
    p.add_argument(
        "--keyframe-spacing-m",
        type=float,
        default=None,
        metavar="M",
        help="keep perceived elements only every M metres of odometry travel (or second); lossy",
    )
    p.add_argument(
        "--point-decimals",
        type=int,
        default=None,
        metavar="D",
        help="decimal digits kept of element points (metres; default 3: 1 mm)",
    )
    p.add_argument(
        "--gzip", action="store_true", help="gzip the output (send it with Content-Encoding: gzip)"
    )
    p.set_defaults(func=_encode)
    d = sub.add_parser("decode-trip", help="convert a compact binary trip upload back into JSON")
    d.add_argument("input", type=Path, help="the binary upload (.cbor or .cbor.gz)")
    d.add_argument("output", type=Path, help="the JSON upload to write")
    d.set_defaults(func=_decode)


def _read(path: Path) -> bytes:
    data = path.read_bytes()
    return gzip.decompress(data) if data[:2] == b"\x1f\x8b" else data


def _encode(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from csr_core import upload_binary
    from csr_core.errors import UploadError
    from csr_core.upload import validate_upload_json

    try:
        doc = validate_upload_json(_read(args.input))
    except UploadError as exc:
        print(f"csr encode-trip: {args.input}: {exc.message}", file=sys.stderr)
        return 2
    options = upload_binary.EncodeOptions(keyframe_spacing_m=args.keyframe_spacing_m)
    if args.point_decimals is not None:
        options = replace(options, decimals=replace(options.decimals, point_m=args.point_decimals))
    try:
        body = upload_binary.encode(doc, options)
    except ValueError as exc:
        print(f"csr encode-trip: {args.input}: {exc}", file=sys.stderr)
        return 2
    out = gzip.compress(body) if args.gzip else body
    args.output.write_bytes(out)
    print(f"{args.input} ({args.input.stat().st_size} bytes) -> {args.output} ({len(out)} bytes)")
    return 0


def _decode(args: argparse.Namespace) -> int:
    import orjson

    from csr_core import upload_binary
    from csr_core.errors import UploadError
    from csr_core.upload import validate_upload

    try:
        doc = validate_upload(upload_binary.decode(_read(args.input)))
    except UploadError as exc:
        print(f"csr decode-trip: {args.input}: {exc.message}", file=sys.stderr)
        return 2
    args.output.write_bytes(orjson.dumps(doc))
    return 0
