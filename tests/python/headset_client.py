#!/usr/bin/env python3
"""Independent reference headset client for the mrptv live protocol, version 1.

Written from protocol/README.md (live protocol) and protocol/recording.md (recording format)
only, without reading the server's source, as a test of the specification.

Streaming mode: send a recording (PNG images as on disk, poses converted from OpenCV to the
session's convention) to /v1/ingest with at most 2 frames unanswered, decode and check every
vector batch, validate every JSON message against protocol/schema, and write the refined vectors
(converted back to OpenCV) as frame,t_s,track_id,x,y,z,u,v,w:

    headset_client.py --url ws://127.0.0.1:8770/v1/ingest --rec REC --out OUT.csv [--convention unity]

Golden mode: validate DIR/*.json against the schemas and decode DIR/frame*.bin, DIR/batch*.bin:

    headset_client.py --check-golden protocol/golden --schemas protocol/schema

Exit 0 when everything checks, 1 with a message otherwise.
"""
import argparse, csv, glob, json, math, os, struct, sys, time, tomllib

import jsonschema
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

FRAME_HDR = struct.Struct("<4sBBHQdII")     # 32 bytes: magic, version, encoding, flags, index, t_s, lens
BATCH_HDR = struct.Struct("<4sBBBBIIQdII")  # 40 bytes: magic, version, kind, convention, flags, session,
                                            #           count, frame_index, t_s, processing_us, age_us
RECORD = struct.Struct("<Q3f3ffHH")         # 40 bytes: track_id, x y z, u v w, residual, flags, reserved
POSE = struct.Struct("<16d")
CONVENTIONS = {"opencv": (0, (1, 1, 1)), "unity": (1, (1, -1, 1)), "webxr": (2, (1, -1, -1))}
KINDS = {1: "causal", 2: "refined"}
TIMEOUT = 30.0
MAX_UNANSWERED = 2
POSE_COLS = [f"world_from_rig_{r}{c}" for r in range(4) for c in range(4)]
DEFAULT_SCHEMAS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "protocol", "schema")


class Failure(Exception):
    pass


_validators = {}


def validate(schemas, name, msg):
    """Validate msg against SCHEMAS/<name>.schema.json (draft 2020-12); a missing schema fails."""
    if name not in _validators:
        path = os.path.join(schemas, name + ".schema.json")
        if not os.path.isfile(path):
            raise Failure(f"no schema file {path} for message {json.dumps(msg)[:200]}")
        with open(path) as f:
            schema = json.load(f)
        jsonschema.Draft202012Validator.check_schema(schema)
        _validators[name] = jsonschema.Draft202012Validator(schema)
    errors = sorted(_validators[name].iter_errors(msg), key=lambda e: list(e.absolute_path))
    if errors:
        e = errors[0]
        raise Failure(f"{name} schema violation at /{'/'.join(map(str, e.absolute_path))}: "
                      f"{e.message} (message: {json.dumps(msg)[:300]})")


def convert_pose(m, signs):
    """F * M * F with F = diag(signs, 1): OpenCV <-> the convention (F is its own inverse)."""
    f = tuple(signs) + (1,)
    return [f[r] * f[c] * m[4 * r + c] for r in range(4) for c in range(4)]


def check_rigid(m, what):
    rot = [[m[4 * r + c] for c in range(3)] for r in range(3)]
    for i in range(3):
        for j in range(3):
            dot = sum(rot[k][i] * rot[k][j] for k in range(3))
            if abs(dot - (i == j)) > 1e-5:
                raise Failure(f"{what}: rotation not orthonormal")
    det = (rot[0][0] * (rot[1][1] * rot[2][2] - rot[1][2] * rot[2][1])
           - rot[0][1] * (rot[1][0] * rot[2][2] - rot[1][2] * rot[2][0])
           + rot[0][2] * (rot[1][0] * rot[2][1] - rot[1][1] * rot[2][0]))
    if det < 0 or m[12:16] != [0.0, 0.0, 0.0, 1.0]:
        raise Failure(f"{what}: not a rigid transform (det {det}, bottom row {m[12:16]})")


def decode_frame(data, what="frame"):
    """Decode a stereo frame message; checks the layout and exact length."""
    if len(data) < FRAME_HDR.size:
        raise Failure(f"{what}: {len(data)} bytes, shorter than the 32-byte header")
    magic, version, enc, flags, index, t_s, llen, rlen = FRAME_HDR.unpack_from(data)
    if magic != b"MRPF" or version != 1 or enc not in (0, 1, 2) or flags & ~1:
        raise Failure(f"{what}: bad header magic={magic!r} version={version} encoding={enc} flags={flags}")
    off = FRAME_HDR.size + (POSE.size if flags & 1 else 0)
    if len(data) != off + llen + rlen:
        raise Failure(f"{what}: {len(data)} bytes, header says {off + llen + rlen}")
    pose = list(POSE.unpack_from(data, FRAME_HDR.size)) if flags & 1 else None
    if pose:
        check_rigid(pose, what)
    left, right = data[off:off + llen], data[off + llen:]
    if enc == 1 and not (left.startswith(b"\x89PNG\r\n\x1a\n") and right.startswith(b"\x89PNG\r\n\x1a\n")):
        raise Failure(f"{what}: encoding png but an image is not a PNG file")
    if enc == 2:
        for image in (left, right):
            # sparse: u8 block_px >= 1, three zero bytes, u32 run count (the rest needs the size).
            if len(image) < 8 or image[0] == 0 or image[1:4] != b"\0\0\0":
                raise Failure(f"{what}: encoding sparse but an image's header is not sparse's")
    return dict(index=index, t_s=t_s, encoding=("raw8", "png", "sparse")[enc], pose=pose, left_len=llen, right_len=rlen)


def decode_batch(data, convention=None, session=None, what="batch"):
    """Decode a vector batch; checks magic, version, kind, convention, length, flags, age, reserved."""
    if len(data) < BATCH_HDR.size:
        raise Failure(f"{what}: {len(data)} bytes, shorter than the 40-byte header")
    magic, version, kind, conv, flags, sess, count, index, t_s, proc_us, age_us = BATCH_HDR.unpack_from(data)
    bad = []
    if magic != b"MRPV": bad.append(f"magic {magic!r}")
    if version != 1: bad.append(f"version {version}")
    if kind not in KINDS: bad.append(f"kind {kind}")
    if conv not in (0, 1, 2) or (convention is not None and conv != convention):
        bad.append(f"convention {conv} (session's: {convention})")
    if session is not None and sess != session: bad.append(f"session number {sess} (welcome: {session})")
    sigmas = flags & 2  # velocity errors after the records (asked for with "uncertainty": true)
    if flags & ~3: bad.append(f"unknown batch flags {flags:#x}")
    if len(data) != BATCH_HDR.size + (RECORD.size + (12 if sigmas else 0)) * count:
        bad.append(f"{len(data)} bytes for {count} records{' with sigmas' if sigmas else ''}")
    if not math.isfinite(t_s): bad.append(f"t_s {t_s}")
    if age_us < proc_us: bad.append(f"age_us {age_us} < processing_us {proc_us} (age includes processing)")
    if bad:
        raise Failure(f"{what}: malformed ({'; '.join(bad)})")
    world = flags & 1
    records = []
    for i in range(count):
        tid, x, y, z, u, v, w, res, rflags, rres = RECORD.unpack_from(data, BATCH_HDR.size + RECORD.size * i)
        if (rflags & 1) != (kind == 2) or ((rflags >> 1) & 1) != world or rres:
            raise Failure(f"{what}: record {i} flags {rflags:#x} / reserved {rres} disagree with "
                          f"kind {KINDS[kind]} and batch world flag {world}")
        if not all(map(math.isfinite, (x, y, z, u, v, w, res))) or res < 0:
            raise Failure(f"{what}: record {i} has non-finite or negative numbers")
        records.append((tid, (x, y, z), (u, v, w), res))
    errors = []
    if sigmas:
        at = BATCH_HDR.size + RECORD.size * count
        for i in range(count):
            s3 = struct.unpack_from("<3f", data, at + 12 * i)
            if not all(math.isfinite(v) and v >= 0 for v in s3):
                raise Failure(f"{what}: vector {i} has sigmas {s3}: not finite and non-negative")
            errors.append(s3)
    return dict(sigmas=errors if sigmas else None,kind=KINDS[kind], convention=conv, world=bool(world), session=sess, frame_index=index,
                t_s=t_s, processing_us=proc_us, records=records)


def read_recording(rec):
    with open(os.path.join(rec, "rig.json")) as f:
        rig = json.load(f)
    with open(os.path.join(rec, "frames.csv"), newline="") as f:
        rows = list(csv.reader(f))
    header = rows[0]
    if header not in (["index", "t_s"], ["index", "t_s"] + POSE_COLS):
        raise Failure(f"frames.csv: unexpected header {header}")
    frames = [(int(r[0]), float(r[1]), [float(x) for x in r[2:]] if len(header) > 2 else None)
              for r in rows[1:] if r]
    toml_path = os.path.join(rec, "mrptv.toml")
    config = None
    if os.path.exists(toml_path):
        with open(toml_path, "rb") as f:
            config = tomllib.load(f)
    return rig, frames, config


def png_bytes(path, width, height):
    with open(path, "rb") as f:
        data = f.read()
    # IHDR: width, height (big-endian u32), bit depth, colour type; 8-bit grayscale is (8, 0).
    if data[:8] != b"\x89PNG\r\n\x1a\n" or struct.unpack(">IIBB", data[16:26]) != (width, height, 8, 0):
        raise Failure(f"{path}: not an 8-bit grayscale {width}x{height} PNG")
    return data


def stream(args):
    rig, frames, config = read_recording(args.rec)
    code, signs = CONVENTIONS[args.convention]
    width, height = rig["image_size"]
    hello = {"type": "hello", "protocol": 1, "client": "mrptv python reference client (tests/python)",
             "rig": rig, "image": {"width": width, "height": height, "encoding": "png"},
             "convention": args.convention}
    if config is not None:
        hello["config"] = config
    validate(args.schemas, "headset-hello", hello)

    unanswered, answered, refined_seen = set(), set(), set()
    refined, errors, dropped, last_bye = [], [], [], []
    n = dict(causal=0, refined=0, causal_vectors=0, refined_vectors=0)
    progress = [time.monotonic()]  # last message other than status: status alone must not keep us waiting

    def receive(ws, expect):
        try:
            msg = ws.recv(timeout=max(0.0, progress[0] + TIMEOUT - time.monotonic()))
        except TimeoutError:
            raise Failure(f"no progress for {TIMEOUT} s while waiting for {expect}; "
                          f"unanswered frames {sorted(unanswered)}")
        except ConnectionClosed as e:
            raise Failure(f"connection closed while waiting for {expect}: {e}")
        if isinstance(msg, bytes):
            progress[0] = time.monotonic()
            return None, msg
        try:
            obj = json.loads(msg)
        except json.JSONDecodeError:
            raise Failure(f"text message is not JSON: {msg[:200]!r}")
        if not isinstance(obj, dict) or not isinstance(obj.get("type"), str):
            raise Failure(f"text message without a string type: {msg[:200]}")
        validate(args.schemas, "server-" + obj["type"], obj)
        if obj["type"] != "status":
            progress[0] = time.monotonic()
        if obj["type"] == "error":
            errors.append(obj)
            print(f"server error: {obj['code']}: {obj['message']}", file=sys.stderr)
        return obj, None

    def handle(ws, expect):
        """Receive one message and account for it; returns the JSON message's type or 'batch'."""
        obj, data = receive(ws, expect)
        if data is not None:
            b = decode_batch(data, code, session_number, f"batch #{n['causal'] + n['refined']}")
            i = b["frame_index"]
            if b["kind"] == "causal":
                if i not in unanswered:
                    raise Failure(f"causal batch for frame {i}, which is not awaiting an answer")
                unanswered.discard(i); answered.add(i)
                n["causal"] += 1; n["causal_vectors"] += len(b["records"])
            else:
                if i not in answered or i in refined_seen or (refined and i <= refined[-1]["frame_index"]):
                    raise Failure(f"refined batch for frame {i}: not a processed frame, repeated or out of order")
                refined_seen.add(i); refined.append(b)
                n["refined"] += 1; n["refined_vectors"] += len(b["records"])
            return "batch"
        if obj["type"] == "bye":
            last_bye[:] = [obj]
        elif obj["type"] == "error" and obj.get("frame_index") in unanswered:
            unanswered.discard(obj["frame_index"])
        elif obj["type"] == "dropped":
            for i in obj["frame_indices"]:
                if i not in unanswered:
                    raise Failure(f"dropped lists frame {i}, which is not awaiting an answer")
                unanswered.discard(i); dropped.append(i)
        return obj["type"]

    try:
        ws = connect(args.url, max_size=64 << 20, open_timeout=TIMEOUT, close_timeout=TIMEOUT, proxy=None)
    except Exception as e:
        raise Failure(f"cannot connect to {args.url}: {e}")
    with ws:
        ws.send(json.dumps(hello))
        while True:
            obj, data = receive(ws, "welcome")
            if data is not None:
                raise Failure("binary message before welcome")
            if obj["type"] == "error":
                raise Failure(f"hello refused: {obj['code']}: {obj['message']}")
            if obj["type"] == "welcome":
                break
        if obj["convention"] != args.convention:
            raise Failure(f"welcome convention {obj['convention']!r}, asked for {args.convention!r}")
        session_number = obj["session_number"]

        for index, t_s, pose in frames:
            while len(unanswered) >= MAX_UNANSWERED:
                handle(ws, f"answers to frames {sorted(unanswered)}")
            left = png_bytes(os.path.join(args.rec, "left", f"{index:06d}.png"), width, height)
            right = png_bytes(os.path.join(args.rec, "right", f"{index:06d}.png"), width, height)
            msg = FRAME_HDR.pack(b"MRPF", 1, 1, 1 if pose else 0, index, t_s, len(left), len(right))
            if pose:
                msg += POSE.pack(*convert_pose(pose, signs))
            ws.send(msg + left + right)
            unanswered.add(index)
            progress[0] = time.monotonic()
        ws.send(json.dumps({"type": "bye"}))
        progress[0] = time.monotonic()
        while handle(ws, "the server's bye") != "bye":
            pass
        counters = last_bye[0].get("counters")
        if counters is None:
            raise Failure("the server's bye after a session carries no counters")
        seen = dict(frames_processed=n["causal"], frames_dropped=len(dropped), queue_depth=0)
        if counters["batches_dropped"] == 0:  # vectors_sent counts causal and refined vectors (not in the spec)
            seen["vectors_sent"] = n["causal_vectors"] + n["refined_vectors"]
        wrong = {k: (counters[k], v) for k, v in seen.items() if counters[k] != v}
        if wrong:
            raise Failure(f"final counters disagree with what was received (counter, seen): {wrong}")
        try:
            extra = ws.recv(timeout=TIMEOUT)
            raise Failure(f"message after the server's bye: {extra[:100]!r}")
        except TimeoutError:
            raise Failure(f"no close within {TIMEOUT} s of the server's bye")
        except ConnectionClosed as e:
            if e.rcvd is None or e.rcvd.code != 1000:
                raise Failure(f"server closed with {e.rcvd} instead of 1000")

    with open(args.out, "w", newline="") as f:
        out = csv.writer(f, lineterminator="\n")
        out.writerow(["frame", "t_s", "track_id", "x", "y", "z", "u", "v", "w"])
        for b in refined:
            for tid, pos, vel, _ in b["records"]:
                back = [s * c for s, c in zip(signs + signs, pos + vel)]  # the sign flip is its own inverse
                out.writerow([b["frame_index"], repr(b["t_s"]), tid] + [repr(float(c)) for c in back])
    print(f"sent {len(frames)} frames; batches: {n['causal']} causal, {n['refined']} refined; vectors: "
          f"{n['causal_vectors']} causal, {n['refined_vectors']} refined; errors {len(errors)}; "
          f"dropped {len(dropped)}")
    if unanswered:
        raise Failure(f"frames never answered: {sorted(unanswered)}")
    if errors:
        raise Failure(f"{len(errors)} error message(s) from the server, first: {errors[0]}")


def check_golden(directory, schemas):
    failures, checked = 0, 0
    for path in sorted(glob.glob(os.path.join(directory, "*.json")) + glob.glob(os.path.join(directory, "*.bin"))):
        name = os.path.basename(path)
        stem = name.rsplit(".", 1)[0]
        checked += 1
        try:
            if name.endswith(".json"):
                with open(path) as f:
                    msg = json.load(f)
                direction = stem.split("-", 1)[0]
                if direction not in ("headset", "server", "viewer"):
                    raise Failure(f"file name does not start with headset-, server- or viewer-")
                if not isinstance(msg, dict) or not isinstance(msg.get("type"), str):
                    raise Failure("not a JSON object with a string type")
                prefix = f"{direction}-{msg['type']}"
                if stem != prefix and not stem.startswith(prefix + "-"):
                    raise Failure(f"type {msg['type']!r} disagrees with the file name (expected {prefix}[-...])")
                validate(schemas, prefix, msg)
                print(f"ok   {name}: {prefix} valid")
            elif stem.startswith("frame"):
                fr = decode_frame(open(path, "rb").read(), name)
                print(f"ok   {name}: frame {fr['index']} t_s={fr['t_s']!r} {fr['encoding']} "
                      f"left {fr['left_len']} B right {fr['right_len']} B pose={fr['pose']}")
            elif stem.startswith("batch"):
                b = decode_batch(open(path, "rb").read(), what=name)
                print(f"ok   {name}: {b['kind']} batch, session {b['session']}, frame {b['frame_index']} "
                      f"t_s={b['t_s']!r}, convention {b['convention']}, world={b['world']}, "
                      f"processing {b['processing_us']} us, {len(b['records'])} records")
                for tid, pos, vel, res in b["records"]:
                    print(f"       track {tid}: pos {pos} vel {vel} residual {res}")
            else:
                raise Failure("binary golden file name starts with neither 'frame' nor 'batch'")
        except (Failure, ValueError, OSError) as e:
            failures += 1
            print(f"FAIL {name}: {e}")
    if not checked:
        raise Failure(f"no *.json or *.bin files in {directory}")
    if failures:
        raise Failure(f"{failures} of {checked} golden files failed")
    print(f"all {checked} golden files ok")


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--url", help="ws://HOST:PORT/v1/ingest")
    p.add_argument("--rec", help="recording directory (rig.json, frames.csv, left/, right/)")
    p.add_argument("--out", help="CSV of the refined vectors, OpenCV convention")
    p.add_argument("--convention", choices=sorted(CONVENTIONS), default="unity")
    p.add_argument("--schemas", default=DEFAULT_SCHEMAS, help="directory of *.schema.json")
    p.add_argument("--check-golden", metavar="DIR", help="check the golden messages in DIR instead")
    args = p.parse_args()
    try:
        if args.check_golden:
            check_golden(args.check_golden, args.schemas)
        elif args.url and args.rec and args.out:
            stream(args)
        else:
            p.error("give --url, --rec and --out, or --check-golden DIR")
    except Failure as e:
        print(f"FAIL: {e}", file=sys.stderr)
        sys.exit(1)


if __name__ == "__main__":
    main()
