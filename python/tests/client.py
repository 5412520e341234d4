"""The Python client against real daemons (run by tests/tests/e2e/python.rs):

    python client.py GENERATOR_ADDR RECORDING_DIR

Every case prints one line; an assertion failure exits non-zero. Checks: pushes of each dtype
arrive; a 256 MiB float32 field is sent without a copy (peak RSS grows by < 10 % of it); bad
input raises the exception the stubs name, with a message naming the problem, and the client
goes on; a closed client refuses; a dead daemon is UnreachableError; the viz-node's recording
reads back every step, and any step's picture."""

import resource
import sys

import numpy as np

import insitu
from check import raises


def peak_rss():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def main():
    addr = sys.argv[1]
    raises(insitu.UnreachableError, "127.0.0.1:1 is unreachable", lambda: insitu.Client("127.0.0.1:1"))
    with insitu.Client(addr) as c:
        z, y, x = np.meshgrid(*(np.arange(16.0),) * 3, indexing="ij")
        ball = np.maximum(0.0, 6.0 - np.sqrt((x - 7.5) ** 2 + (y - 7.5) ** 2 + (z - 7.5) ** 2))
        for step, dtype in enumerate([np.float32, np.float64, np.uint8, np.uint16, np.int16]):
            reply = c.push(step, (ball * 40).astype(dtype), sim_time=step * 0.5)
            assert reply["steps_received"] == step + 1, reply
        print("pushed 5 dtypes")
        raises(TypeError, "float16", lambda: c.push(9, ball.astype(np.float16)))
        raises(TypeError, ">f4", lambda: c.push(9, ball.astype(">f4")))
        raises(TypeError, "numpy.ndarray, not list", lambda: c.push(9, [1.0, 2.0]))
        raises(ValueError, "2 dimensions", lambda: c.push(9, np.zeros((4, 4), np.float32)))
        raises(ValueError, "not C-contiguous", lambda: c.push(9, ball.astype(np.float32)[:, :, ::2]))
        raises(ValueError, "not C-contiguous", lambda: c.push(9, np.asfortranarray(ball.astype(np.float32))))
        raises(ValueError, "offset", lambda: c.push(9, ball.astype(np.float32), offset=(-1, 0, 0)))
        raises(
            insitu.RefusedError,
            "does not fit in the grid",
            lambda: c.push(9, ball.astype(np.float32), offset=(8, 0, 0), global_dims=(16, 16, 16)),
        )
        raises(insitu.RefusedError, "rank 2 with world_size 2", lambda: c.push(9, ball.astype(np.float32), rank=2, world_size=2))
        # Zero copy: the field's bytes are read in place (peak RSS grows by far less than it).
        big = np.ones((64, 1024, 1024), np.float32)
        before = peak_rss()
        c.push(10, big)
        grew = peak_rss() - before
        print(f"zero copy: a {big.nbytes >> 20} MiB push raised peak RSS by {grew / 2**20:.1f} MiB")
        assert grew < 0.1 * big.nbytes, grew
        status = c.flush(timeout=120)
        assert status["steps_received"] == 6 and status["steps_shipped"] == 6, status
        print("flushed", status)
    assert c.closed
    raises(ValueError, "is closed", lambda: c.push(11, ball.astype(np.float32)))
    assert c.close() is None, "closing twice does nothing"
    rec = insitu.Recording(sys.argv[2])
    assert [s["step"] for s in rec.steps] == [0, 1, 2, 3, 4, 10], rec.steps
    assert all(s["r"] == 32 and s["sigma_bytes"] > 0 and s["world_size"] == 1 for s in rec.steps)
    picture = rec.image(2, size=40, angle=30.0)
    assert picture.shape == (40, 40, 3) and float(picture.max()) > 0.05, picture.max()
    assert np.array_equal(picture, rec.vdi(2).render(size=40, angle=30.0))
    print(f"recording: {len(rec)} steps, step 2's picture lit")
    raises(KeyError, "no step 99", lambda: rec.image(99))
    raises(ValueError, "missing", lambda: insitu.Recording(sys.argv[2] + "/missing"))
    print("ok")


if __name__ == "__main__":
    main()
