#!/usr/bin/env python3
"""Streams a circle in XY to a machine's CNC as G05 binary blocks, honouring the credits.

The same contract as `cellgate g05` (proto/cellgate/v1/g05.proto), with eclipse-zenoh and the
classes gen.sh generates:

  1. open a zenoh session: client mode, one connect endpoint, no listen, no multicast scouting;
  2. get on P/C/machine/M/g05 with a G05Open (producer_token set): the reply is G05Opened
     (block length, credits, axes, unit time T), or an ErrorReply;
  3. declare the liveliness token P/C/machine/M/g05/S/producer: should this script die, the
     gateway ends the stream cleanly (end block) instead of leaving the CNC starved;
  4. subscribe to the stream's G05Status on P/C/machine/M/g05/S (at least every 100 ms);
  5. put G05Batch messages on P/C/machine/M/g05/S/blocks, never more blocks than the credits
     allow (the credits of the last status, less what was sent since);
  6. send the last batch with end set, and wait for the final status.

Exit codes: 0 the stream completed; 1 it failed or no gateway answered; 2 refused.

    ./g05_circle.py --machine mill-2 --blocks 3000 --radius 2000
"""

import argparse
import math
import queue
import sys

import submit
from submit import encoding, find_cell, open_session

BATCH = 200


def circle(blocks: int, radius: float, axes: int):
    """Relative travels of a circle in XY (the other axes still), never an all-zero block."""
    px, py = round(radius), 0
    for i in range(1, blocks + 1):
        a = 2 * math.pi * i / blocks
        x, y = round(radius * math.cos(a)), round(radius * math.sin(a))
        dx, dy = x - px, y - py
        if dx == 0 and dy == 0:
            dy = 1
        px, py = px + dx, py + dy
        yield [dx, dy] + [0] * (axes - 2)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("-m", "--machine", required=True, help="a machine with [machines.g05]")
    ap.add_argument("-e", "--connect", default="tcp/127.0.0.1:7447", help="the gateway's zenoh endpoint")
    ap.add_argument("--prefix", default="cellgate", help="the gateway's key prefix (bus.prefix)")
    ap.add_argument("--cell", help="the cell (default: the only one answering)")
    ap.add_argument("--blocks", type=int, default=3000, help="blocks of the circle")
    ap.add_argument("--radius", type=float, default=2000.0, help="in least input increments")
    args = ap.parse_args()
    # After the arguments, so that --help works before `pip install` and ./gen.sh.
    submit.load_dependencies()
    zenoh, error_pb2 = submit.zenoh, submit.error_pb2
    try:
        from cellgate.v1 import g05_pb2
    except ImportError:
        sys.exit("the generated classes are missing: run ./gen.sh first")
    done = (g05_pb2.G05_STATE_COMPLETED, g05_pb2.G05_STATE_FAILED)

    try:
        z = open_session(args.connect)
    except zenoh.ZError as e:
        print(f"cannot connect to {args.connect}: {e}", file=sys.stderr)
        return 1
    with z:
        cell = args.cell
        if cell is None:
            cells = find_cell(z, args.prefix)
            if len(cells) != 1:
                print(f"cells answering: {', '.join(cells) or 'none'}; name one with --cell", file=sys.stderr)
                return 1
            cell = cells[0]
        base = f"{args.prefix}/{cell}/machine/{args.machine}/g05"

        opened = None
        request = g05_pb2.G05Open(producer_token=True)
        for reply in z.get(base, payload=request.SerializeToString(), encoding=encoding("G05Open"), timeout=10):
            if reply.ok is not None:
                opened = g05_pb2.G05Opened.FromString(reply.ok.payload.to_bytes())
            else:
                err = error_pb2.ErrorReply.FromString(reply.err.payload.to_bytes())
                print(f"refused ({error_pb2.ErrorCode.Name(err.code)}): {err.message}", file=sys.stderr)
                return 2
        if opened is None:
            print(f"no gateway answered on {base}", file=sys.stderr)
            return 1
        if opened.axes < 2:
            print(f"{args.machine} takes {opened.axes} axis: a circle needs two", file=sys.stderr)
            return 2
        stream = f"{base}/{opened.stream_id}"
        print(
            f"stream {opened.stream_id}: {opened.axes} axes, T = {opened.unit_time_ms} ms, "
            f"window {opened.window}, priming {opened.prime}, "
            f"{opened.actual_baud} baud for {opened.required_baud} needed"
        )
        token = z.liveliness().declare_token(f"{stream}/producer")
        statuses: queue.Queue = queue.Queue()
        sub = z.declare_subscriber(stream, statuses.put)

        latest = g05_pb2.G05Status(credits=opened.credits)
        sent = 0
        seq = 0
        path = list(circle(args.blocks, args.radius, opened.axes))
        while True:
            credits = latest.credits - max(0, sent - latest.received)
            n = min(credits, BATCH, len(path) - sent)
            last = sent + n == len(path)
            if n > 0 or last:
                batch = g05_pb2.G05Batch(seq=seq, end=last)
                for travel in path[sent : sent + n]:
                    batch.blocks.add(travel=travel)
                z.put(f"{stream}/blocks", batch.SerializeToString(), encoding=encoding("G05Batch"))
                sent += n
                seq += 1
                if last:
                    break
                continue
            # No credits left: wait for the next status.
            sample = statuses.get(timeout=30)
            latest = g05_pb2.G05Status.FromString(sample.payload.to_bytes())
            if latest.state in done:
                break
        while latest.state not in done:
            sample = statuses.get(timeout=120)
            latest = g05_pb2.G05Status.FromString(sample.payload.to_bytes())
        sub.undeclare()
        token.undeclare()
        state = g05_pb2.G05State.Name(latest.state)
        print(
            f"{state}: {latest.received} blocks, {latest.underruns} underruns (estimated)"
            + (f"; {latest.last_error}" if latest.last_error else "")
        )
        return 0 if latest.state == g05_pb2.G05_STATE_COMPLETED else 1


if __name__ == "__main__":
    sys.exit(main())
