"""Size and transport: oversize bodies (declared or chunked) -> 413, malformed multipart and
too many parts / fields -> 400 quickly; nothing stored changes and /healthz stays 200.
"""

from __future__ import annotations

import json
import socket
import threading
import time

import pytest

from tests.reliability_helpers import assert_error, assert_healthy

MAX_BODY = 8 << 20


SERVER = {"max_body_bytes": MAX_BODY}  # the shared server fixture's settings (tests/service/conftest.py)


def _raw_post(port: int, path: str, head_lines: list[str], body_chunks, *, chunked: bool) -> tuple[int, dict, float]:
    """Send a request over a raw socket while a thread reads the answer; returns
    (status, json body, seconds until the first answer byte). The server may answer and close
    before the whole body went out, which is the point of the test."""
    received = bytearray()
    first_byte = []
    start = time.perf_counter()

    def read(sock):
        try:
            while data := sock.recv(65536):
                if not first_byte:
                    first_byte.append(time.perf_counter() - start)
                received.extend(data)
        except OSError:
            pass

    head = f"POST {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n" + "".join(
        f"{line}\r\n" for line in head_lines) + "\r\n"
    with socket.create_connection(("127.0.0.1", port), timeout=30) as sock:
        reader = threading.Thread(target=read, args=(sock,))
        reader.start()
        try:
            sock.sendall(head.encode())
            for chunk in body_chunks:
                if received:
                    break
                sock.sendall(f"{len(chunk):x}\r\n".encode() + chunk + b"\r\n" if chunked else chunk)
            if chunked and not received:
                sock.sendall(b"0\r\n\r\n")
        except OSError:
            pass
        reader.join(30)
    header, _, body = bytes(received).partition(b"\r\n\r\n")
    status = int(header.split()[1])
    if b"transfer-encoding: chunked" in header.lower():
        body = body.split(b"\r\n")[1]
    return status, json.loads(body), first_byte[0]


def _multipart(parts: list[tuple[str, str | None, bytes]], boundary: str = "rel-boundary") -> bytes:
    out = bytearray()
    for name, filename, data in parts:
        disposition = f'form-data; name="{name}"' + (f'; filename="{filename}"' if filename else "")
        out += f"--{boundary}\r\nContent-Disposition: {disposition}\r\n\r\n".encode() + data + b"\r\n"
    out += f"--{boundary}--\r\n".encode()
    return bytes(out)


MP = {"Content-Type": "multipart/form-data; boundary=rel-boundary"}


def test_declared_body_over_limit_is_413_before_reading(s):
    before = s.stored()
    start = time.perf_counter()
    r = s.client.post("/scenes", files={"archive": ("a.zip", b"\x00" * (MAX_BODY + 1))})
    message = assert_error(r, 413, "payload_too_large")
    assert str(MAX_BODY) in message
    assert time.perf_counter() - start < 5
    # Same on /enhance and on the checkpoint upload: the limit sits in front of every route.
    for path in ("/enhance", f"/scenes/{s.scene_id}/checkpoints"):
        assert_error(s.client.post(path, files={"x": ("x", b"\x00" * (MAX_BODY + 10))}), 413, "payload_too_large")
    assert s.stored() == before
    assert_healthy(s.client)


def test_chunked_body_without_content_length_is_cut_at_the_limit(s):
    before = s.stored()
    first = (b'--rel-boundary\r\nContent-Disposition: form-data; name="archive"; filename="a.zip"\r\n'
             b"Content-Type: application/zip\r\n\r\n")
    # 2x the limit is offered; the server must answer after ~MAX_BODY, not wait for the rest.
    chunks = [first] + [b"z" * 65536] * (2 * MAX_BODY // 65536)
    status, body, seconds = _raw_post(s.live.port, "/scenes",
                                      ["Transfer-Encoding: chunked", f"Content-Type: {MP['Content-Type']}"],
                                      chunks, chunked=True)
    assert status == 413 and body["error"]["code"] == "payload_too_large", body
    assert seconds < 10
    assert s.stored() == before
    assert_healthy(s.client)


@pytest.mark.parametrize("case, content_type, body, needle", [
    ("no_boundary", "multipart/form-data", b"--x\r\n\r\n", "boundary"),
    ("garbage", MP["Content-Type"], b"this is not multipart at all", "multipart"),
    ("bad_header", MP["Content-Type"], b"--rel-boundary\r\nno colon here\r\n\r\nx\r\n--rel-boundary--\r\n", ""),
])
def test_malformed_multipart_is_400(s, case, content_type, body, needle):
    before = s.stored()
    r = s.client.post("/scenes", content=body, headers={"Content-Type": content_type})
    assert needle.lower() in assert_error(r, 400, "bad_request").lower()
    r = s.client.post("/enhance", content=body, headers={"Content-Type": content_type})
    assert_error(r, 400, "bad_request")
    assert s.stored() == before
    assert_healthy(s.client)


def test_truncated_multipart_names_the_missing_part(s):
    """A body cut before its closing boundary holds no complete part: 422 naming the field
    (python-multipart drops the unfinished part; it does not flag the truncation itself)."""
    before = s.stored()
    body = b'--rel-boundary\r\nContent-Disposition: form-data; name="archive"; filename="a.zip"\r\n\r\nPK'
    r = s.client.post("/scenes", content=body, headers=MP)
    assert "archive" in assert_error(r, (400, 422))
    assert s.stored() == before


@pytest.mark.parametrize("what, parts, needle", [
    ("files", [("archive", f"a{i}.zip", b"x") for i in range(5)], "Too many files"),
    ("fields", [(f"f{i}", None, b"v") for i in range(17)], "Too many fields"),
    ("tiny_parts", [(f"f{i}", None, b"") for i in range(20_000)], "Too many fields"),
    ("big_field", [("scene_id", None, b"a" * ((1 << 20) + 1))], ""),
])
def test_too_many_parts_or_fields_is_400_quickly(s, what, parts, needle):
    before = s.stored()
    body = _multipart(parts)
    assert len(body) < MAX_BODY
    start = time.perf_counter()
    r = s.client.post("/enhance", content=body, headers=MP)
    seconds = time.perf_counter() - start
    assert needle in assert_error(r, 400, "bad_request")
    assert seconds < 2.0, f"{what}: {seconds:.2f} s"
    assert s.stored() == before
    assert_healthy(s.client)


def test_not_multipart_at_all_is_422_naming_the_fields(s):
    before = s.stored()
    r = s.client.post("/scenes", content=b'{"archive": "x"}', headers={"Content-Type": "application/json"})
    assert "archive" in assert_error(r, 422, "validation_error")
    assert s.stored() == before


def test_urlencoded_form_limits_hold_too(s):
    """Starlette < 1.3.1 ignored max_fields / max_part_size for urlencoded bodies
    (GHSA-82w8-qh3p-5jfq); a form route must refuse 20 000 urlencoded fields quickly."""
    before = s.stored()
    body = "&".join(f"f{i}=v" for i in range(20_000)).encode()
    start = time.perf_counter()
    r = s.client.post("/enhance", content=body, headers={"Content-Type": "application/x-www-form-urlencoded"})
    assert "Too many fields" in assert_error(r, 400, "bad_request")
    assert time.perf_counter() - start < 2.0
    big = b"camera=" + b"a" * ((1 << 20) + 1)
    assert_error(s.client.post("/enhance", content=big, headers={"Content-Type": "application/x-www-form-urlencoded"}),
                 400, "bad_request")
    assert s.stored() == before
