"""An independent OPC UA client of the cell's server, with asyncua (PyPI), run by the tests.

  opcua_client.py check URL NODESETS     every CNC under Machines has every mandatory node
                                         of MachineToolType (read from the NodeSet files),
                                         each with its type; prints "checked N nodes"
  opcua_client.py follow URL MACHINE     prints "ready", then "value Name|State TEXT" for
                                         each data change and "event CODE SEVERITY SOURCE"
                                         for each event of the Server object, until killed
  opcua_client.py write URL MACHINE      tries to write ActiveProgram.Name; prints the status
  opcua_client.py login URL [USER PASS]  opens a session (anonymous without USER); prints
                                         "ok" or "refused STATUS"
  opcua_client.py secure URL USER PASS DIR
                                         opens a Basic256Sha256 SignAndEncrypt session with a
                                         client certificate made in DIR (kept for a second
                                         try); prints "ok" or "refused STATUS"
  opcua_client.py monitor URL            subscribes to every machine tool's ActiveProgram Name
                                         and State (1 s publishing), prints "ready", runs
                                         until killed
  opcua_client.py events URL             prints "ready", then "event TYPE" for each event of
                                         the Server object (its EventType's BrowseName)
  opcua_client.py units URL PLC TAG      prints the tag's value type and its EngineeringUnits:
                                         "TYPE UNIT_ID SYMBOL", or "TYPE none"
  opcua_client.py names URL              the BrowseNames under Machines, sorted, one a line
  opcua_client.py status URL MACHINE     the status of the machine's ChannelState value
"""

import asyncio
import glob
import os
import sys
import xml.etree.ElementTree as ET

from asyncua import Client, ua

UA = "http://opcfoundation.org/UA/"
X = {"u": "http://opcfoundation.org/UA/2011/03/UANodeSet.xsd"}
HIERARCHICAL = {"i=47", "i=46", "i=17604", "i=35", "i=49"}
HAS_TYPE_DEFINITION, HAS_MODELLING_RULE, HAS_SUBTYPE, MANDATORY = "i=40", "i=37", "i=45", "i=78"


def load(folder):
    """Every node of the NodeSet files in `folder`: (uri, id) -> node."""
    nodes = {}
    for path in sorted(glob.glob(os.path.join(folder, "*.xml"))):
        root = ET.parse(path).getroot()
        uris = [UA] + [u.text for u in root.findall("u:NamespaceUris/u:Uri", X)]
        aliases = {a.get("Alias"): a.text for a in root.findall("u:Aliases/u:Alias", X)}

        def nid(text):
            text = aliases.get(text, text)
            if text.startswith("ns="):
                ns, rest = text[3:].split(";", 1)
                return (uris[int(ns)], rest)
            return (UA, text)

        for el in root:
            if not el.tag.endswith(("UAObject", "UAVariable", "UAObjectType", "UAVariableType")):
                continue
            browse = el.get("BrowseName")
            ns, name = browse.split(":", 1) if ":" in browse and browse.split(":", 1)[0].isdigit() else ("0", browse)
            refs = []
            for r in el.findall("u:References/u:Reference", X):
                refs.append((nid(r.get("ReferenceType"))[1], nid(r.text.strip()), r.get("IsForward", "true") != "false"))
            nodes[nid(el.get("NodeId"))] = {"uri": uris[int(ns)], "name": name, "refs": refs}
    return nodes


def first(nodes, node, ref, forward=True):
    for t, target, fwd in nodes.get(node, {}).get("refs", []):
        if t == ref and fwd == forward:
            return target
    return None


def mandatory(nodes, sources):
    """The Mandatory children the instance declarations or types `sources` give."""
    out = {}
    for s in sources:
        chain, t = [], s
        while t in nodes and len(chain) < 16:
            chain.append(t)
            t = first(nodes, t, HAS_SUBTYPE, forward=False)
        for t in chain:
            for ref, child, fwd in nodes[t]["refs"]:
                if not fwd or ref not in HIERARCHICAL or child not in nodes:
                    continue
                if first(nodes, child, HAS_MODELLING_RULE) != (UA, MANDATORY):
                    continue
                c = nodes[child]
                out.setdefault((c["uri"], c["name"]), []).append(child)
    return out


async def check(url, folder):
    nodes = load(folder)
    async with Client(url=url) as client:
        ns = await client.get_namespace_array()
        machine_tool = (ns.index("http://opcfoundation.org/UA/MachineTool/"), "i=13")
        folder_node = client.get_node(f"ns={ns.index('http://opcfoundation.org/UA/Machinery/')};i=1001")
        checked, missing, cncs = 0, [], 0
        for m in await folder_node.get_children():
            t = await m.read_type_definition()
            if (t.NamespaceIndex, f"i={t.Identifier}") != machine_tool:
                continue
            cncs += 1
            todo = [(m, [("http://opcfoundation.org/UA/MachineTool/", "i=13")], "")]
            while todo:
                node, sources, path = todo.pop()
                for (uri, name), decls in mandatory(nodes, sources).items():
                    at = f"{path}/{name}"
                    try:
                        child = await node.get_child([f"{ns.index(uri)}:{name}"])
                    except Exception:
                        missing.append(f"{(await m.read_browse_name()).Name}{at}: missing")
                        continue
                    checked += 1
                    want = first(nodes, decls[0], HAS_TYPE_DEFINITION)
                    got = await child.read_type_definition()
                    if want and got is not None and (ns[got.NamespaceIndex], f"i={got.Identifier}") != want:
                        missing.append(f"{at}: type {got}, the NodeSet says {want}")
                    more = list(decls) + ([want] if want in nodes else [])
                    todo.append((child, more, at))
        if cncs == 0 or missing:
            print("\n".join(missing) or "no machine tool under Machines")
            sys.exit(1)
        print(f"checked {checked} nodes of {cncs} machine tools")


class Printer:
    def __init__(self, names):
        self.names = names

    def datachange_notification(self, node, val, data):
        text = val.Text if isinstance(val, ua.LocalizedText) else val
        print(f"value {self.names.get(node.nodeid.to_string(), '?')} {text}", flush=True)

    def event_notification(self, event):
        code = getattr(event, "Identifier", None)
        print(f"event {code} {event.Severity} {event.SourceName}", flush=True)


async def follow(url, machine):
    async with Client(url=url) as client:
        ns = await client.get_namespace_array()
        folder_node = client.get_node(f"ns={ns.index('http://opcfoundation.org/UA/Machinery/')};i=1001")
        mt = ns.index("http://opcfoundation.org/UA/MachineTool/")
        m = None
        for c in await folder_node.get_children():
            if (await c.read_browse_name()).Name == machine:
                m = c
        program = await m.get_child([f"{mt}:Production", f"{mt}:ActiveProgram"])
        name = await program.get_child([f"{mt}:Name"])
        state = await program.get_child([f"{mt}:State", "0:CurrentState"])
        handler = Printer({name.nodeid.to_string(): "Name", state.nodeid.to_string(): "State"})
        sub = await client.create_subscription(100, handler)
        await sub.subscribe_data_change([name, state])
        notification = await client.nodes.root.get_child(
            ["0:Types", "0:EventTypes", "0:BaseEventType", f"{mt}:NotificationEventType"]
        )
        # Without a where clause: async-opcua 0.19 compares no NodeIds in InList, the
        # operator asyncua's generated clause uses (docs/opcua.md).
        await sub.subscribe_events(client.nodes.server, notification, where_clause_generation=False)
        print("ready", flush=True)
        while True:
            await asyncio.sleep(1)


async def write(url, machine):
    async with Client(url=url) as client:
        ns = await client.get_namespace_array()
        mt = ns.index("http://opcfoundation.org/UA/MachineTool/")
        folder_node = client.get_node(f"ns={ns.index('http://opcfoundation.org/UA/Machinery/')};i=1001")
        for c in await folder_node.get_children():
            if (await c.read_browse_name()).Name == machine:
                name = await c.get_child([f"{mt}:Production", f"{mt}:ActiveProgram", f"{mt}:Name"])
        try:
            await name.write_value(ua.DataValue(ua.Variant("O9999", ua.VariantType.String)))
            print("written")
        except ua.UaStatusCodeError as e:
            print(f"refused {ua.StatusCode(e.code).name}")


async def attempt(client):
    """Opens a session with `client` and reads one value; prints "ok" or "refused STATUS"."""
    try:
        await client.connect()
        await client.get_namespace_array()
        await client.disconnect()
        print("ok")
    except ua.UaStatusCodeError as e:
        print(f"refused {ua.StatusCode(e.code).name}")
    except Exception as e:
        print(f"refused {type(e).__name__} {e}")


async def login(url, user=None, password=None):
    client = Client(url=url)
    if user is not None:
        client.set_user(user)
        client.set_password(password)
    await attempt(client)


async def secure(url, user, password, folder):
    from cryptography.x509.oid import ExtendedKeyUsageOID
    from asyncua.crypto.cert_gen import setup_self_signed_certificate

    uri = "urn:cellgate:tests:client"
    from pathlib import Path

    cert, key = Path(folder) / "client.der", Path(folder) / "client.pem"
    await setup_self_signed_certificate(
        key_file=key,
        cert_file=cert,
        app_uri=uri,
        host_name="localhost",
        cert_use=[ExtendedKeyUsageOID.CLIENT_AUTH],
        subject_attrs={"commonName": "cellgate tests"},
    )
    client = Client(url=url)
    client.application_uri = uri
    client.set_user(user)
    client.set_password(password)
    await client.set_security_string(f"Basic256Sha256,SignAndEncrypt,{cert},{key}")
    await attempt(client)


async def machines(client):
    ns = await client.get_namespace_array()
    folder_node = client.get_node(f"ns={ns.index('http://opcfoundation.org/UA/Machinery/')};i=1001")
    return ns, await folder_node.get_children()


class Quiet:
    def datachange_notification(self, node, val, data):
        pass


async def monitor(url):
    async with Client(url=url, timeout=60) as client:
        ns, found = await machines(client)
        mt = ns.index("http://opcfoundation.org/UA/MachineTool/")
        items = []
        for m in found:
            try:
                program = await m.get_child([f"{mt}:Production", f"{mt}:ActiveProgram"])
            except Exception:
                continue  # a PLC
            items.append(await program.get_child([f"{mt}:Name"]))
            items.append(await program.get_child([f"{mt}:State", "0:CurrentState"]))
        sub = await client.create_subscription(1000, Quiet())
        await sub.subscribe_data_change(items)
        print("ready", len(items), flush=True)
        while True:
            await asyncio.sleep(1)


class Types:
    def __init__(self, names):
        self.names = names

    def event_notification(self, event):
        print(f"event {self.names.get(event.EventType.to_string(), event.EventType)}", flush=True)


async def events(url):
    async with Client(url=url) as client:
        ns = await client.get_namespace_array()
        mt = ns.index("http://opcfoundation.org/UA/MachineTool/")
        names = {
            ua.NodeId(ua.ObjectIds.BaseModelChangeEventType).to_string(): "BaseModelChangeEventType",
            ua.NodeId(35, mt).to_string(): "NotificationEventType",
        }
        sub = await client.create_subscription(100, Types(names))
        await sub.subscribe_events(client.nodes.server)
        print("ready", flush=True)
        while True:
            await asyncio.sleep(1)


async def units(url, plc, tag):
    async with Client(url=url) as client:
        ns, found = await machines(client)
        cells = ns.index("urn:cellgate:cells")
        for m in found:
            if (await m.read_browse_name()).Name == plc:
                node = await m.get_child([f"{cells}:{tag}"])
                kind = (await (client.get_node(await node.read_type_definition())).read_browse_name()).Name
                try:
                    eu = await (await node.get_child(["0:EngineeringUnits"])).read_value()
                    print(kind, eu.UnitId, eu.DisplayName.Text)
                except ua.UaStatusCodeError:
                    print(kind, "none")


async def names(url):
    async with Client(url=url) as client:
        _, found = await machines(client)
        print("\n".join(sorted([(await m.read_browse_name()).Name for m in found])))


async def status(url, machine):
    async with Client(url=url) as client:
        ns, found = await machines(client)
        mt = ns.index("http://opcfoundation.org/UA/MachineTool/")
        for m in found:
            if (await m.read_browse_name()).Name == machine:
                cells = ns.index("urn:cellgate:cells")
                state = await m.get_child([f"{mt}:Monitoring", f"{cells}:Channel1", f"{mt}:ChannelState"])
                value = await state.read_data_value(raise_on_bad_status=False)
                print(value.StatusCode.name)


if __name__ == "__main__":
    cmd, args = sys.argv[1], sys.argv[2:]
    asyncio.run({
        "check": check,
        "follow": follow,
        "write": write,
        "login": login,
        "names": names,
        "units": units,
        "events": events,
        "monitor": monitor,
        "secure": secure,
        "status": status,
    }[cmd](*args))
