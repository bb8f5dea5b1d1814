#!/usr/bin/env python3
"""Follows a cellgate MTConnect agent with the standard library only (docs/mtconnect.md).

  1. GET /current: every data item's state, and the buffer's nextSequence and instanceId;
  2. GET /sample?from=NEXT&count=N again and again: the observations since, each page's
     nextSequence saying where the next one starts;
  3. print each EXECUTION, PROGRAM, PART_COUNT and condition (with its nativeCode) as it
     changes; when instanceId changes (the agent restarted), start over from /current;
     an OUT_OF_RANGE error (the client fell a whole buffer behind) starts over too.

    ./mtconnect_follow.py http://127.0.0.1:5000 [--device mill-1] [--once]

Exit codes: 0 on --once after the first document; 1 when the agent cannot be reached.
"""

import argparse
import sys
import time
import urllib.error
import urllib.parse
import urllib.request
import xml.etree.ElementTree as ET

SHOWN = {"Execution", "Program", "PartCount", "Availability"}
LEVELS = {"Normal", "Warning", "Fault", "Unavailable"}


def fetch(url):
    """The document at url as an element tree; an MTConnectError's code as an exception."""
    try:
        with urllib.request.urlopen(url, timeout=10) as r:
            body = r.read()
    except urllib.error.HTTPError as e:
        body = e.read()
    root = ET.fromstring(body)
    if root.tag.endswith("MTConnectError"):
        codes = [e.get("errorCode") for e in root.iter() if e.tag.endswith("}Error")]
        raise LookupError(",".join(c for c in codes if c))
    return root


def header(root):
    return next(e for e in root.iter() if e.tag.endswith("}Header")).attrib


def observations(root):
    """(device, element, dataItemId, sequence, value, nativeCode) in sequence order."""
    out = []
    for stream in (e for e in root.iter() if e.tag.endswith("}DeviceStream")):
        for obs in stream.iter():
            if "dataItemId" not in obs.attrib:
                continue
            element = obs.tag.split("}")[1]
            out.append((stream.get("name"), element, obs.get("dataItemId"),
                        int(obs.get("sequence")), (obs.text or "").strip(),
                        obs.get("nativeCode", "")))
    return sorted(out, key=lambda o: o[3])


def show(obs):
    device, element, item, seq, value, code = obs
    if element in LEVELS:
        print(f"{seq:>8} {device:<12} {item:<24} {element} {code} {value}".rstrip())
    elif element in SHOWN:
        print(f"{seq:>8} {device:<12} {item:<24} {value}")


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("agent", help="the agent's URL, e.g. http://127.0.0.1:5000")
    p.add_argument("--device", help="one device, by name or UUID")
    p.add_argument("--count", type=int, default=500, help="observations per page")
    p.add_argument("--every", type=float, default=1.0, help="seconds between pages")
    p.add_argument("--once", action="store_true", help="print /current and stop")
    a = p.parse_args()
    base = a.agent.rstrip("/") + ("/" + urllib.parse.quote(a.device) if a.device else "")
    while True:
        try:
            root = fetch(base + "/current")
        except (OSError, LookupError) as e:
            print(f"mtconnect_follow: {base}/current: {e}", file=sys.stderr)
            return 1
        h = header(root)
        instance, nxt = h["instanceId"], int(h["nextSequence"])
        for o in observations(root):
            show(o)
        if a.once:
            return 0
        while True:
            time.sleep(a.every)
            try:
                page = fetch(f"{base}/sample?from={nxt}&count={a.count}")
            except LookupError as e:
                print(f"mtconnect_follow: {e}: starting over", file=sys.stderr)
                break
            except OSError as e:
                print(f"mtconnect_follow: {e}", file=sys.stderr)
                return 1
            h = header(page)
            if h["instanceId"] != instance:
                print("mtconnect_follow: the agent restarted: starting over", file=sys.stderr)
                break
            for o in observations(page):
                show(o)
            nxt = int(h["nextSequence"])


if __name__ == "__main__":
    sys.exit(main())
