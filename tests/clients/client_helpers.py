"""What the client tests share: PNG, the bytes the mock transport of conftest.sent answers with; multipart_parts, the
parts of a request the client sent."""

PNG = b"\x89PNG\r\n\x1a\n" + b"\0" * 32


def multipart_parts(request) -> dict[str, tuple[str, bytes]]:
    """{part name: (content type, bytes)} of a multipart request (an httpx.Request)."""
    from email.parser import BytesParser
    from email.policy import HTTP

    head = f"Content-Type: {request.headers['content-type']}\r\n\r\n".encode()
    msg = BytesParser(policy=HTTP).parsebytes(head + request.read())
    return {m.get_param("name", header="content-disposition"): (m.get_content_type(), m.get_payload(decode=True))
            for m in msg.iter_parts()}
