"""What the Python tests share (run from python/tests: `python client.py …`, `python offline.py …`)."""


def raises(kind, words, f):
    """Calls f; asserts it raises `kind` with `words` in its message, and prints the message."""
    try:
        f()
    except kind as e:
        assert words in str(e), f"{kind.__name__}: {e!r} lacks {words!r}"
        print(f"{kind.__name__}: {e}")
        return
    raise AssertionError(f"no {kind.__name__} (wanted one mentioning {words!r})")
