#!/usr/bin/env python3
"""Sends an NC program to a machine of a cellgate cell and follows the job to its end.

The same contract as `cellgate submit`, with eclipse-zenoh and the classes gen.sh generates
from proto/cellgate/v1:

  1. open a zenoh session: client mode, connect to one endpoint only, no listen endpoint,
     multicast scouting off; on a tls/ endpoint, check the gateway's certificate against
     --tls-ca and show this client's own (--tls-cert, --tls-key) to a gateway that asks;
  2. find the cell (the only gateway answering P/*/@admin), unless --cell names it;
  3. subscribe to P/C/machine/M/job/* *before* sending the request, so that no event of the
     job is missed (its id is only known from the reply);
  4. get on P/C/machine/M/submit with a JobRequest: the reply is JobAccepted, or an ErrorReply;
  5. print the job's events until it completes, fails or is cancelled. When nothing arrives
     for a while (a job waiting in the queue is silent), ask for its latest event with a get
     on P/C/machine/M/job/ID.

Exit codes: 0 the program was delivered; 1 it failed or was cancelled, or no gateway
answered; 2 the gateway refused the request (the ErrorReply is printed).

    ./submit.py --machine mill-1 ../programs/O1234.nc
    ./submit.py --machine mill-1 --connect tls/127.0.0.1:7447 --tls-ca tls/ca.pem \
        --tls-cert ../tls/mes-1.pem --tls-key ../tls/mes-1-key.pem ../programs/O1234.nc
"""

from __future__ import annotations

import argparse
import json
import os
import queue
import sys
import uuid

# Imported by load_dependencies() once the arguments are parsed, so that --help works before
# `pip install` and ./gen.sh.
zenoh = None
error_pb2 = None
job_pb2 = None

SILENCE_S = 5.0
SUBMIT_TIMEOUT_S = 60.0


def load_dependencies() -> None:
    """Imports eclipse-zenoh and the classes gen.sh generates, or exits saying what is missing."""
    global zenoh, error_pb2, job_pb2
    try:
        import zenoh as zenoh_module
    except ImportError:
        sys.exit("the eclipse-zenoh package is missing: pip install -r requirements.txt")
    zenoh = zenoh_module
    sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "gen"))
    try:
        from cellgate.v1 import error_pb2 as error_module, job_pb2 as job_module
    except ImportError:
        sys.exit("the generated classes are missing: run ./gen.sh first")
    error_pb2, job_pb2 = error_module, job_module


def encoding(message_name: str) -> zenoh.Encoding:
    """application/protobuf with the message's full name as schema, as the gateway expects."""
    return zenoh.Encoding.APPLICATION_PROTOBUF.with_schema(f"cellgate.v1.{message_name}")


def open_session(endpoint: str, ca=None, cert=None, key=None) -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("scouting/multicast/enabled", "false")
    if ca:
        # The CA that signed the gateway's certificate; the gateway's certificate must also
        # name the endpoint's host.
        conf.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(ca))
    if cert and key:
        # This client's certificate: its common name is what the gateway's roles name.
        conf.insert_json5("transport/link/tls/enable_mtls", "true")
        conf.insert_json5("transport/link/tls/connect_certificate", json.dumps(cert))
        conf.insert_json5("transport/link/tls/connect_private_key", json.dumps(key))
    return zenoh.open(conf)


def find_cell(z: zenoh.Session, prefix: str) -> list[str]:
    """The cells whose gateways answer their admin key P/<cell>/@admin."""
    cells = set()
    for reply in z.get(f"{prefix}/*/@admin", consolidation=zenoh.ConsolidationMode.NONE, timeout=10):
        if reply.ok is not None:
            key = str(reply.ok.key_expr)
            cells.add(key[len(prefix) + 1 : -len("/@admin")])
    return sorted(cells)


def gateway_cells(z: zenoh.Session, prefix: str) -> list[str]:
    """The cells whose gateways' liveliness tokens P/<cell>/gateway stand."""
    cells = set()
    for reply in z.liveliness().get(f"{prefix}/*/gateway", timeout=10):
        if reply.ok is not None:
            key = str(reply.ok.key_expr)
            cells.add(key[len(prefix) + 1 : -len("/gateway")])
    return sorted(cells)


def describe(event) -> str:
    kind = event.WhichOneof("kind")
    if kind == "queued":
        return f"queued ({event.queued.queue_position} ahead)"
    if kind == "started":
        total = event.started.bytes_total if event.started.HasField("bytes_total") else "?"
        return f"started ({total} bytes)"
    if kind == "progress":
        p = event.progress
        total = p.bytes_total if p.HasField("bytes_total") else 0
        percent = f" ({p.bytes_sent * 100 // total}%)" if total else ""
        return f"sent {p.bytes_sent} of {total or '?'} bytes{percent}, {p.rate_bps} B/s"
    if kind == "completed":
        c = event.completed
        text = f"completed: {c.bytes_sent} bytes in {c.duration_ms / 1000:.1f} s"
        if c.bytes_after_eor:
            # A line end after the last %: the CNC ignores it, so it is not sent.
            text += f"; {c.bytes_after_eor} byte after the EOR % not sent (the CNC ignores it)"
        return text
    if kind == "failed":
        f = event.failed
        alarm = f" [{f.alarm_number}]" if f.alarm_number else ""
        code = error_pb2.ErrorCode.Name(f.code)
        return f"failed at byte {f.byte_offset}: {f.reason}{alarm} ({code})"
    if kind == "cancelled":
        return f"cancelled by {event.cancelled.by} at byte {event.cancelled.byte_offset}"
    return "event of an unknown kind"


def latest_event(z: zenoh.Session, key: str, job_id: str):
    for reply in z.get(key, timeout=10):
        if reply.ok is not None:
            event = job_pb2.JobEvent.FromString(reply.ok.payload.to_bytes())
            if event.job_id == job_id:
                return event
    return None


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("file", help="the NC program (sent inline: read whole into memory)")
    ap.add_argument("-m", "--machine", required=True, help="the machine's name in the cell file")
    ap.add_argument("-e", "--connect", default="tcp/127.0.0.1:7447", help="the gateway's zenoh endpoint")
    ap.add_argument("--prefix", default="cellgate", help="the gateway's key prefix (bus.prefix)")
    ap.add_argument("--cell", help="the cell (default: the only one answering)")
    ap.add_argument("--name", default="", help="the name shown in status and events")
    ap.add_argument("--priority", type=int, default=0, help="higher runs first (default 0)")
    ap.add_argument("--append-eor", action="store_true", help="append %% (EOR) if the program lacks it")
    ap.add_argument("--request-id", default=None, help="idempotency key (default: a new UUID)")
    ap.add_argument("--tls-ca", default=os.environ.get("CELLGATE_TLS_CA"),
                    help="the CA that signed the gateway's certificate (PEM), for a tls/ endpoint")
    ap.add_argument("--tls-cert", default=os.environ.get("CELLGATE_TLS_CERT"),
                    help="this client's certificate (PEM), for a gateway that requires one")
    ap.add_argument("--tls-key", default=os.environ.get("CELLGATE_TLS_KEY"),
                    help="the private key of --tls-cert (PEM)")
    args = ap.parse_args()
    if args.connect.startswith("tls/") and not args.tls_ca:
        ap.error("a tls/ endpoint needs --tls-ca, the CA that signed the gateway's certificate")
    if bool(args.tls_cert) != bool(args.tls_key):
        ap.error("give both --tls-cert and --tls-key, or neither")
    load_dependencies()

    with open(args.file, "rb") as f:
        program = f.read()
    # A request id makes the submit idempotent: if the reply is lost and this script (or a
    # retry of it) sends the same request again, the gateway answers the first JobAccepted
    # and queues nothing twice.
    request = job_pb2.JobRequest(
        inline=program,
        name=args.name,
        priority=args.priority,
        append_eor=args.append_eor,
        request_id=args.request_id or uuid.uuid4().hex,
    )

    try:
        z = open_session(args.connect, args.tls_ca, args.tls_cert, args.tls_key)
    except zenoh.ZError as e:
        hint = " (over TLS: a gateway that requires client certificates refuses a client " \
            "without one signed by its CA)" if args.connect.startswith("tls/") else ""
        print(f"cannot connect to {args.connect}: is `cellgate run` running there?{hint} ({e})",
              file=sys.stderr)
        return 1
    with z:
        cell = args.cell
        if cell is None:
            # A gateway with roles shows @admin only to admin.read; its liveliness token
            # stands for every role.
            cells = find_cell(z, args.prefix) or gateway_cells(z, args.prefix)
            if len(cells) != 1:
                found = ", ".join(cells) if cells else "none"
                print(f"cells answering at {args.connect}: {found}; name one with --cell", file=sys.stderr)
                return 1 if not cells else 2
            cell = cells[0]
        base = f"{args.prefix}/{cell}/machine/{args.machine}"

        # Subscribed before the request goes out: the subscription and the request travel in
        # order on the one link to the gateway.
        events: queue.Queue = queue.Queue()
        sub = z.declare_subscriber(f"{base}/job/*", events.put)

        accepted = None
        for reply in z.get(
            f"{base}/submit",
            payload=request.SerializeToString(),
            encoding=encoding("JobRequest"),
            timeout=SUBMIT_TIMEOUT_S,
        ):
            if reply.ok is not None:
                accepted = job_pb2.JobAccepted.FromString(reply.ok.payload.to_bytes())
            else:
                err = error_pb2.ErrorReply.FromString(reply.err.payload.to_bytes())
                print(f"refused ({error_pb2.ErrorCode.Name(err.code)}): {err.message}", file=sys.stderr)
                return 2
        if accepted is None:
            print(f"no gateway answered on {base}/submit (on a cell with roles, this client's "
                  "certificate needs job.submit)", file=sys.stderr)
            return 1
        job = accepted.job_id
        print(f"accepted: job {job}, {accepted.queue_position} job(s) ahead")

        while True:
            try:
                sample = events.get(timeout=SILENCE_S)
            except queue.Empty:
                event = latest_event(z, f"{base}/job/{job}", job)
                if event is None:
                    print(f"the gateway no longer answers for job {job}", file=sys.stderr)
                    return 1
                if event.WhichOneof("kind") not in ("completed", "failed", "cancelled"):
                    continue
            else:
                if sample.kind != zenoh.SampleKind.PUT:
                    continue  # a cancel request (a delete on the job's key)
                event = job_pb2.JobEvent.FromString(sample.payload.to_bytes())
                if event.job_id != job:
                    continue  # another job of the same machine
            print(f"{job}: {describe(event)}")
            kind = event.WhichOneof("kind")
            if kind in ("completed", "failed", "cancelled"):
                sub.undeclare()
                return 0 if kind == "completed" else 1


if __name__ == "__main__":
    sys.exit(main())
