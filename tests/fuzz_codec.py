"""Coverage-guided fuzzing of ``wire_codec.decode`` with atheris (``make fuzz``).

Not a pytest module (the name does not start with ``test_``, and nothing runs on import).
Run::

    .venv/bin/python -m pip install atheris
    .venv/bin/python tests/fuzz_codec.py -atheris_runs=200000 [CORPUS_DIR ...]

The first input byte picks what the rest is:

* 0: a whole payload, as is;
* 1: a body, sealed into a valid robot-map envelope (correct CRC), so that the fuzzer reaches
  the bit parser; short bodies are also decoded by the literal reference decoder, and the two
  must agree (both reject, or the same map);
* 2: the same for a fused-map envelope with three robots;
* 3: a payload whose last five bytes are replaced by a correct CRC (envelope fuzzing past the
  checksum).

Anything but a :class:`wire_codec.CodecError` escaping the decoder is a crash. Without corpus
directories it seeds a temporary one with the golden vectors; crash files go to a temporary
directory (printed at start) unless ``-artifact_prefix=`` is given. Bodies it has found are
kept as regression cases in ``tests/test_codec_hostile.py::test_fuzzer_finds_stay_fixed``.
"""

from __future__ import annotations

import json
import sys
import tempfile
import zlib
from pathlib import Path

import msgpack

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> int:
    try:
        import atheris
    except ImportError:
        sys.stderr.write("atheris is not installed: .venv/bin/python -m pip install atheris\n")
        return 1

    with atheris.instrument_imports():
        import wire_codec
        from wire_codec import reference
        from wire_codec.codec import decode_with
        from wire_codec.errors import DEFAULT_LIMITS

    seeds = {
        v["name"]: bytes.fromhex(v["hex"])
        for version in wire_codec.VERSIONS
        for v in json.loads(
            (Path(__file__).with_name("golden") / f"codec_v{version}.json").read_text()
        )["vectors"]
    }
    robot_fields = list(msgpack.unpackb(seeds["room_mixed"], raw=False)[:-1])
    fused_fields = list(msgpack.unpackb(seeds["fused_three_robots"], raw=False)[:-1])

    def seal(fields: list[object], body: bytes) -> bytes:
        fields = list(fields)
        fields[11] = body
        head = b"\x9d" + msgpack.packb(fields, use_bin_type=True)[1:]
        return head + b"\xce" + zlib.crc32(head).to_bytes(4, "big")

    def outcome(payload: bytes, body_decoder: object = None) -> object:
        try:
            if body_decoder is None:
                return wire_codec.decode(payload)
            return decode_with(payload, DEFAULT_LIMITS, body_decoder)  # type: ignore[arg-type]
        except wire_codec.CodecError:
            return None

    def one_input(data: bytes) -> None:
        if not data:
            return
        mode, rest = data[0] % 4, data[1:]
        if mode == 0:
            outcome(rest)
        elif mode in (1, 2):
            payload = seal(robot_fields if mode == 1 else fused_fields, rest)
            fast = outcome(payload)
            if len(rest) <= 256:
                slow = outcome(payload, reference.decode_body)
                if (fast is None) != (slow is None):
                    raise AssertionError(f"fast and reference decoders disagree on body {rest.hex()}")
                if fast is not None and slow is not None:
                    a, b = fast.wireframe, slow.wireframe  # type: ignore[attr-defined]
                    if not (a.points.tolist() == b.points.tolist() and a.edges.tolist() == b.edges.tolist()
                            and a.likelihood.tolist() == b.likelihood.tolist()
                            and a.sources.tolist() == b.sources.tolist()
                            and a.labels.tolist() == b.labels.tolist()):
                        raise AssertionError(f"fast and reference decoders read body {rest.hex()} "
                                             "differently")
        else:
            head = rest[:-5] if len(rest) > 5 else rest
            outcome(head + b"\xce" + zlib.crc32(head).to_bytes(4, "big"))

    argv = list(sys.argv)
    if not any(a.startswith("-artifact_prefix=") for a in argv):  # keep crash files out of the checkout
        artifacts = tempfile.mkdtemp(prefix="wire_codec_fuzz_artifacts_")
        argv.append(f"-artifact_prefix={artifacts}/")
        sys.stderr.write(f"crash artifacts go to {artifacts}/\n")
    if not any(not a.startswith("-") for a in argv[1:]):
        corpus = tempfile.mkdtemp(prefix="wire_codec_fuzz_")
        for name, payload in seeds.items():
            body = msgpack.unpackb(payload, raw=False)[11]
            Path(corpus, f"{name}.0").write_bytes(b"\x00" + payload)
            Path(corpus, f"{name}.1").write_bytes(b"\x01" + body)
            Path(corpus, f"{name}.2").write_bytes(b"\x02" + body)
            Path(corpus, f"{name}.3").write_bytes(b"\x03" + payload)
        argv.append(corpus)
        sys.stderr.write(f"seed corpus: {corpus}\n")
    atheris.Setup(argv, one_input)
    atheris.Fuzz()
    return 0


if __name__ == "__main__":
    sys.exit(main())
