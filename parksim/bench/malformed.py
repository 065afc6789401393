"""Malformed requests to ``parksim serve``: a fixed corpus of hand-made bad ``/render`` requests, seeded random ones,
and the raw-HTTP sender that delivers each on its own loopback connection (``parksim bench hardening``).

Every probe is valid HTTP/1.1 and valid but for the one thing it breaks (its ``name``), so the server must answer it
4xx with a JSON ``detail``. Bytes that are not HTTP (a non-ASCII request line) are left out: uvicorn's protocol layer
answers those with a plain-text 400 before the app sees them.
"""

from __future__ import annotations

import contextlib
import http.client
import json
import socket
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["Probe", "Reply", "corpus", "send", "probe_all"]

_TIMEOUT_S = 60.0
_BIG_BODY = 2 * 2**20
"""A body twice the server's default ``max_body_bytes``."""


@dataclass(frozen=True)
class Probe:
    """One malformed request, sent as raw bytes on its own connection.

    Attributes:
        group: what it attacks (``pose``, ``scale``, ``body``, ``host``, ``key`` ...), for the counts per group.
        name: what is wrong with it, one line.
        method: the HTTP method.
        target: path and query as sent (ASCII: bytes outside it are not HTTP, and uvicorn answers them itself).
        body: the body (a ``Content-Length`` and ``Content-Type: application/json`` are added), or None.
        headers: more header lines, sent as given after the generated ones.
        host: the ``Host`` header; None: the server's own ``127.0.0.1:PORT``.
        keyed: whether the request carries the right API key (the key probes set their own ``headers``).
        chunked: send the body with ``Transfer-Encoding: chunked`` instead of a ``Content-Length``.
    """

    group: str
    name: str
    method: str
    target: str
    body: bytes | None = None
    headers: tuple[tuple[str, str], ...] = ()
    host: str | None = None
    keyed: bool = True
    chunked: bool = False


@dataclass(frozen=True)
class Reply:
    """What the server answered: the status (0: no reply at all), whether the reply is a JSON object with a
    non-empty text ``detail``, and its content type."""

    status: int
    json_detail: bool
    content_type: str


def _get(group: str, name: str, query: str, path: str = "/render", **kw: Any) -> Probe:
    return Probe(group, name, "GET", f"{path}?{query}" if query else path, **kw)


def _post(group: str, name: str, body: bytes | str, **kw: Any) -> Probe:
    return Probe(group, name, "POST", "/render", body.encode() if isinstance(body, str) else body, **kw)


def _poses(*poses: str) -> str:
    """A POST body with these pose texts (JSON fragments) and every other field valid."""
    return '{"poses": [' + ", ".join(poses) + '], "cameras": ["front"], "scale": 0.25}'


def _hand_made(key: str, x: float) -> list[Probe]:
    """The fixed corpus; ``key`` is the server's API key, ``x`` an x inside the garage (the poses are valid but for
    what each probe breaks)."""
    ok = f"{x:g},0,0"
    bad_poses = {"NaN x": "nan,0,0", "NaN y": "0,NaN,0", "NaN yaw": f"{x:g},0,nan", "inf x": "inf,0,0",
                 "-inf y": f"{x:g},-inf,0", "Infinity yaw": f"{x:g},0,Infinity", "1e308 x": "1e308,0,0",
                 "-1e308 y": f"{x:g},-1e308,0", "1e29 x": "1e29,0,0", "1e29 y": f"{x:g},1e29,0",
                 "1e400 x (overflows to inf)": "1e400,0,0", "1e29 z": f"{x:g},0,1e29,0,0,0",
                 "one value": "1", "two values": "1,2", "four values": "1,2,3,4", "five values": "1,2,3,4,5",
                 "seven values": "1,2,3,4,5,6,7", "empty": "", "only commas": ",,", "an empty value": f"{x:g},,0",
                 "text": "a,b,c", "a word": f"{x:g},0,zero", "hex": "0x10,0,0", "digit separator": "1_0,0,0",
                 "Arabic-Indic digits": "%D9%A3,0,0", "full-width digits": "%EF%BC%91,0,0",
                 "trailing junk": f"{x:g},0,0;1", "roll 0.9 rad": f"{x:g},0,0,0.9,0,0",
                 "pitch -0.9 rad": f"{x:g},0,0,0,-0.9,0", "300 characters": "1," * 150,
                 "percent-encoded NUL": f"{x:g},0,0%00", "invalid UTF-8 (percent-encoded 0xff)": "%FF,0,0"}
    probes = [_get("pose", f"GET pose: {name}", f"pose={value}") for name, value in bad_poses.items()]
    probes.append(_get("pose", "GET pose: missing", "cameras=front"))
    bad_params = {"camera: unknown": "cameras=nosuch", "camera: one of two unknown": "cameras=front,nosuch",
                  "camera: wrong case": "cameras=FRONT", "camera: a path": "cameras=../../etc/passwd",
                  "camera: 2000 characters": "cameras=" + "f" * 2000,
                  "scale: 0": "scale=0", "scale: negative": "scale=-1", "scale: NaN": "scale=nan",
                  "scale: inf": "scale=inf", "scale: 1e308": "scale=1e308", "scale: 100": "scale=100",
                  "scale: 0.001": "scale=0.001", "scale: text": "scale=big", "scale: empty": "scale=",
                  "scale: 1e-400 (underflows to 0)": "scale=1e-400",
                  "format: gif": "format=gif", "format: upper case": "format=PNG",
                  "format: png with four views": "format=png", "format: jpeg with no view": "format=jpeg&cameras=",
                  "format: png with a view and the BEV": "format=png&cameras=front&bev=on",
                  "bev: not a boolean": "bev=maybe", "depth: not a boolean": "depth=2",
                  "scene: unknown": "scene=nosuch", "scene: 300 characters": "scene=" + "s" * 300,
                  "query: an unknown parameter": "foo=1", "key: in the query string too": f"api_key={key}"}
    probes += [_get(name.split(":")[0], f"GET {name}", f"pose={ok}&{query}")
               for name, query in bad_params.items()]
    probes += [_get("view", "GET view: unknown camera", f"pose={ok}", "/render/nosuch.png"),
               _get("view", "GET view: gif", f"pose={ok}", "/render/front.gif"),
               _get("view", "GET view: no extension", f"pose={ok}", "/render/front"),
               _get("view", "GET view: pose missing", "", "/render/front.png"),
               _get("view", "GET view: NaN pose", "pose=nan,0,0", "/render/front.png"),
               _get("view", "GET view: 1e29 pose", "pose=1e29,0,0", "/render/bev.jpg"),
               _get("view", "GET view: scale 0", f"pose={ok}&scale=0", "/render/front.png"),
               Probe("method", "PUT /render", "PUT", "/render", b"{}"),
               Probe("method", "DELETE /render", "DELETE", f"/render?pose={ok}"),
               Probe("method", "PATCH /render", "PATCH", "/render", b"{}")]
    nested = 10_000
    bodies = {"malformed: unclosed object": "{", "malformed: unclosed array": '{"poses": [[1, 0, 0]]',
              "malformed: unquoted keys": "{poses: [[1, 0, 0]]}", "malformed: single quotes": "{'poses': [[1,0,0]]}",
              "malformed: trailing comma": '{"poses": [[1, 0, 0],]}', "malformed: two objects": "{}{}",
              "malformed: a comment": '{"poses": [[1, 0, 0]] /* x */}',
              f"arrays nested {nested:,} deep": "[" * nested + "]" * nested,
              f"objects nested {nested:,} deep": '{"a":' * nested + "1" + "}" * nested,
              "poses nested 10,000 deep": '{"poses": ' + "[" * nested + "]" * nested + "}",
              "a 5000-digit integer in a pose": _poses("[" + "9" * 5000 + ", 0, 0]"),
              "a 5000-digit integer as the scale": '{"poses": [[1, 0, 0]], "scale": ' + "1" * 5000 + "}",
              "JSON null": "null", "a JSON list": "[]", "a JSON string": '"render"', "a JSON number": "42",
              "an empty object": "{}", "poses: text": '{"poses": "abc"}', "poses: a number": '{"poses": 1}',
              "poses: empty": '{"poses": []}', "poses: null": '{"poses": null}',
              "pose: two values": _poses("[1, 2]"), "pose: four values": _poses("[1, 2, 3, 4]"),
              "pose: text values": _poses('["a", "b", "c"]'), "pose: a boolean": _poses("[true, 0, 0]"),
              "pose: null values": _poses("[null, 0, 0]"), "pose: nested list": _poses("[[1, 0, 0]]"),
              "pose: object without yaw": _poses('{"x": 1, "y": 0}'),
              "pose: object with an extra key": _poses('{"x": 1, "y": 0, "yaw": 0, "w": 1}'),
              "pose: NaN literal": _poses("[NaN, 0, 0]"), "pose: Infinity literal": _poses("[0, Infinity, 0]"),
              "pose: -Infinity yaw": _poses("[1, 0, -Infinity]"), "pose: 1e308": _poses("[1e308, 0, 0]"),
              "pose: 1e29": _poses("[1e29, 0, 0]"), "pose: 1e400 (overflows to inf)": _poses("[1e400, 0, 0]"),
              "pose: text 'nan'": _poses('["nan", 0, 0]'), "pose: roll 0.9 rad": _poses("[1, 0, 0, 0.9, 0, 0]"),
              "17 poses (max_batch 16)": _poses(*["[1, 0, 0]"] * 17),
              "1025 poses": _poses(*["[1, 0, 0]"] * 1025),
              "scale: text": '{"poses": [[1, 0, 0]], "scale": "big"}',
              "scale: 0": '{"poses": [[1, 0, 0]], "scale": 0}', "scale: -1": '{"poses": [[1, 0, 0]], "scale": -1}',
              "scale: 1e308": '{"poses": [[1, 0, 0]], "scale": 1e308}',
              "cameras: a string": '{"poses": [[1, 0, 0]], "cameras": "front"}',
              "cameras: numbers": '{"poses": [[1, 0, 0]], "cameras": [1, 2]}',
              "cameras: unknown": '{"poses": [[1, 0, 0]], "cameras": ["nosuch"]}',
              "bev: not a boolean": '{"poses": [[1, 0, 0]], "bev": "maybe"}',
              "depth: a number": '{"poses": [[1, 0, 0]], "depth": 2}',
              "scene: a number": '{"poses": [[1, 0, 0]], "scene": 5}',
              "scene: unknown": '{"poses": [[1, 0, 0]], "scene": "nosuch"}',
              "scene: a lone surrogate": '{"poses": [[1, 0, 0]], "scene": "\\ud800"}',
              "an unknown field": '{"poses": [[1, 0, 0]], "foo": 1}', "empty": ""}
    probes += [_post("body", f"POST body: {name}", body) for name, body in bodies.items()]
    probes += [_post("body", "POST body: invalid UTF-8 (0xff)", b'{"poses": [[1, 0, 0]], "scene": "\xff"}'),
               _post("body", "POST body: overlong UTF-8", b'{"poses": [[1, 0, 0]], "scene": "\xc0\xaf"}'),
               _post("body", "POST body: UTF-16 without a byte-order mark", _poses(f"[{x:g}, 0, 0]")
                     .encode("utf-16-le")),
               _post("body", "POST body: UTF-16 with a byte-order mark", _poses(f"[{x:g}, 0, 0]")
                     .encode("utf-16")),
               _post("body", "POST body: 2 MiB", b'{"poses": [' + b" " * _BIG_BODY + b"]}"),
               _post("body", "POST body: no Content-Length (chunked)", b'{"poses": [[1, 0, 0]]}', chunked=True),
               _post("body", "POST body: a valid body sent as text/plain", _poses(f"[{x:g}, 0, 0]"),
                     headers=(("Content-Type", "text/plain"),))]
    for host in ("evil.example", "evil.example:8000", "127.0.0.1.evil.example", "localhost.evil.example:80",
                 "169.254.169.254", ""):
        probes.append(_get("host", f"GET with Host {host!r}", f"pose={ok}", host=host))
    near = key[:-1] + ("a" if key[-1] != "a" else "b")
    keys = {"missing": (), "wrong": (("X-API-Key", "wrong"),), "whitespace only": (("X-API-Key", "   "),),
            "empty": (("X-API-Key", ""),), "last character wrong": (("X-API-Key", near),),
            "a prefix of the key": (("X-API-Key", key[:-1]),), "the key twice": (("X-API-Key", key + key),),
            "upper case": (("X-API-Key", key.upper()),) if key.upper() != key else (("X-API-Key", "X" + key),),
            "as a Bearer token": (("Authorization", f"Bearer {key}"),),
            "in the query string only": ()}
    for name, headers in keys.items():
        query = f"pose={ok}" + (f"&api_key={key}" if "query" in name else "")
        probes.append(_get("key", f"GET key: {name}", query, headers=headers, keyed=False))
    return probes


_JUNK = "abcxyz!$()*+;:=@~-_.'"


def _random(rng: np.random.Generator, n: int, x: float) -> list[Probe]:
    """``n`` seeded malformed requests, each from one of five generators that cannot make a valid request."""
    probes = []
    for i in range(n):
        kind = int(rng.integers(5))
        if kind == 0:   # a pose with junk in one value
            values = [f"{x:g}", "0", "0"]
            values[int(rng.integers(3))] = "".join(rng.choice(list(_JUNK), int(rng.integers(1, 12))))
            probes.append(_get("random", f"random {i}: junk pose value", "pose=" + ",".join(values)))
        elif kind == 1:   # a position of magnitude 1e20..1e400
            values = [f"{x:g}", "0", "0"]
            values[int(rng.integers(2))] = f"{rng.choice([-1, 1]) * 1}e{int(rng.integers(20, 401))}"
            probes.append(_get("random", f"random {i}: huge position", "pose=" + ",".join(values)))
        elif kind == 2:   # a wrong number of values
            count = int(rng.choice([1, 2, 4, 5, 7, 8, 9, 12]))
            pose = ",".join(f"{v:.3f}" for v in rng.uniform(-1, 1, count))
            probes.append(_get("random", f"random {i}: {count} pose values", f"pose={pose}"))
        elif kind == 3:   # a scale outside the server's limits
            scale = float(rng.choice([-1.0, 1.0])) * 10.0 ** float(rng.uniform(-9, -2)) if rng.random() < 0.5 \
                else 10.0 ** float(rng.uniform(0.5, 300))
            probes.append(_get("random", f"random {i}: scale {scale:.3g}", f"pose={x:g},0,0&scale={scale:.6g}"))
        else:   # a valid body cut at a random byte
            body = _poses(f"[{x:g}, 0, 0]").encode()
            probes.append(_post("random", f"random {i}: body cut short", body[:int(rng.integers(1, len(body) - 1))]))
    return probes


def corpus(key: str, x: float, random_probes: int, seed: int) -> list[Probe]:
    """The malformed requests: the hand-made ones, then ``random_probes`` seeded ones.

    Args:
        key: the server's API key (the key probes vary it; every other probe carries it).
        x: an x (m) inside the served garage, so that a probe's pose is valid but for what it breaks.
        random_probes: how many seeded random probes to add.
        seed: their seed.

    Returns:
        The probes, the hand-made ones first, always the same for the same arguments.
    """
    return _hand_made(key, x) + _random(np.random.default_rng(seed), random_probes, x)


def _request_bytes(probe: Probe, host: str, key: str) -> bytes:
    """``probe`` as the bytes of one HTTP/1.1 request (``Connection: close``)."""
    lines = [f"{probe.method} {probe.target} HTTP/1.1", f"Host: {probe.host if probe.host is not None else host}",
             "Connection: close"]
    if probe.keyed:
        lines.append(f"X-API-Key: {key}")
    body = b""
    if probe.body is not None:
        if not any(name.lower() == "content-type" for name, _ in probe.headers):
            lines.append("Content-Type: application/json")
        if probe.chunked:
            lines.append("Transfer-Encoding: chunked")
            body = b"%x\r\n%s\r\n0\r\n\r\n" % (len(probe.body), probe.body)
        else:
            lines.append(f"Content-Length: {len(probe.body)}")
            body = probe.body
    lines += [f"{name}: {value}" for name, value in probe.headers]
    return ("\r\n".join(lines) + "\r\n\r\n").encode("ascii") + body


def send(port: int, probe: Probe, key: str) -> Reply:
    """Send ``probe`` to ``127.0.0.1:port`` on a fresh connection and read the whole reply.

    Args:
        port: the server's port.
        probe: the request.
        key: the server's API key (sent unless ``probe.keyed`` is False).

    Returns:
        The reply; status 0 when the server closed the connection without one.
    """
    with socket.create_connection(("127.0.0.1", port), timeout=_TIMEOUT_S) as sock:
        with contextlib.suppress(OSError):   # a server that answers before reading a large body may close on it
            sock.sendall(_request_bytes(probe, f"127.0.0.1:{port}", key))
        reply = http.client.HTTPResponse(sock, method=probe.method)
        try:
            reply.begin()
            data = reply.read()
        except (OSError, http.client.HTTPException):
            return Reply(0, False, "")
    content_type = reply.getheader("content-type", "")
    try:
        parsed = json.loads(data) if content_type.startswith("application/json") else None
    except ValueError:
        parsed = None
    detail = isinstance(parsed, dict) and isinstance(parsed.get("detail"), str) and bool(parsed["detail"])
    return Reply(reply.status, detail, content_type)


def probe_all(port: int, probes: list[Probe], key: str) -> dict[str, Any]:
    """Send every probe in turn and count the replies.

    Args:
        port: the server's loopback port.
        probes: the requests (``corpus``).
        key: the server's API key.

    Returns:
        ``sent``; ``statuses`` (count per status) and ``groups`` (the same per probe group); ``server_errors``
        (5xx), ``not_4xx`` and ``not_json_detail`` counts; ``odd``: every probe not answered with a JSON 4xx; the
        ``seconds`` taken.
    """
    statuses: dict[str, int] = {}
    groups: dict[str, dict[str, int]] = {}
    odd = []
    start = time.perf_counter()
    for probe in probes:
        reply = send(port, probe, key)
        statuses[str(reply.status)] = statuses.get(str(reply.status), 0) + 1
        counts = groups.setdefault(probe.group, {})
        counts[str(reply.status)] = counts.get(str(reply.status), 0) + 1
        if not 400 <= reply.status < 500 or not reply.json_detail:
            odd.append({"probe": probe.name, "status": reply.status, "content_type": reply.content_type,
                        "json_detail": reply.json_detail})
    return {"sent": len(probes), "statuses": dict(sorted(statuses.items())), "groups": groups,
            "server_errors": sum(n for s, n in statuses.items() if s.startswith("5")),
            "not_4xx": sum(n for s, n in statuses.items() if not s.startswith("4")),
            "not_json_detail": sum(1 for o in odd if not o["json_detail"]), "odd": odd,
            "seconds": time.perf_counter() - start}
