"""What the client tests share: PNG, the bytes the mock transport of conftest.sent answers with."""

PNG = b"\x89PNG\r\n\x1a\n" + b"\0" * 32
