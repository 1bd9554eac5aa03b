"""The pyo3 + numpy bindings: numpy arrays that are the slot memory, leases that cannot outlive
their slot, owner-only shared memory, and refusal of peers with another schema."""
import os
import stat
import uuid

import numpy as np
import pytest

import lmac_shm
from lmac_env.core import schema_path

LBF8 = str(schema_path("lbf:8x8-2p-2f-s1-coop"))
LBF11 = str(schema_path("lbf:11x11-6p-4f-s1-coop"))


@pytest.fixture
def name():
    n = f"lmac-pytest-{uuid.uuid4().hex[:8]}"
    yield n
    lmac_shm.unlink(n)


def test_views_are_the_shared_memory(name):
    owner = lmac_shm.Slab.create(name, LBF8, 4, 29, 3)
    peer = lmac_shm.Slab.open(name, LBF8, timeout=1.0)
    assert owner.schema_hash == peer.schema_hash
    lease = owner.lease(1, "env")
    obs = lease.obs
    assert obs.shape == (4, 2, 29) and obs.dtype == np.float32
    obs[2, 1, 5] = 42.0
    lease.msg[0, 0, 3] = 7.0
    rows = lease.rows
    assert rows[2, 1, 5] == 42.0 and rows[0, 0, 29 + 3] == 7.0  # message columns follow the row
    lease.state[3, 299] = 1.5
    del obs, rows
    lease.release("trainer")
    # The other mapping sees the same bytes without any copy.
    other = peer.lease(1, "trainer")
    assert other.obs[2, 1, 5] == 42.0
    assert other.state[3, 299] == 1.5
    assert peer.stage(1) == "trainer"


def test_lease_is_dead_after_release(name):
    slab = lmac_shm.Slab.create(name, LBF8, 2, 0, 2)
    lease = slab.lease(0, "env")
    lease.release()
    assert slab.stage(0) == "runner"
    with pytest.raises(lmac_shm.SlotReleasedError):
        lease.obs
    with pytest.raises(lmac_shm.SlotReleasedError):
        lease.seq = 3
    # Only the owning stage may lease a slot.
    with pytest.raises(RuntimeError, match="owned by the protocol runner"):
        slab.lease(0, "env")


def test_release_refused_while_views_alive(name):
    slab = lmac_shm.Slab.create(name, LBF8, 2, 0, 2)
    lease = slab.lease(0, "env")
    kept = lease.state
    assert lease.live_views == 1
    with pytest.raises(lmac_shm.SlotViewsAliveError):
        lease.release()
    assert slab.stage(0) == "env"  # nothing was handed over
    del kept
    assert lease.live_views == 0
    lease.release()


def test_views_keep_mapping_alive(name):
    slab = lmac_shm.Slab.create(name, LBF8, 2, 0, 2)
    arr = slab.lease(0, "env").avail
    del slab  # the view still holds the mapping: no read of freed memory
    arr[:] = 1
    assert arr.sum() == arr.size


def test_owner_only_mode_and_unlink_on_drop(name):
    slab = lmac_shm.Slab.create(name, LBF8, 2, 0, 2)
    path = f"/dev/shm/{name}"
    assert stat.S_IMODE(os.stat(path).st_mode) == 0o600
    del slab
    assert not os.path.exists(path)


def test_peer_with_other_schema_is_refused(name):
    _owner = lmac_shm.Slab.create(name, LBF8, 2, 29, 2)
    with pytest.raises(RuntimeError, match="disagree on the schema"):
        lmac_shm.Slab.open(name, LBF11, timeout=1.0)


def test_existing_name_is_not_clobbered(name):
    _owner = lmac_shm.Slab.create(name, LBF8, 2, 0, 2)
    with pytest.raises(RuntimeError, match="File exists"):
        lmac_shm.Slab.create(name, LBF8, 2, 0, 2)


def test_bad_schema_file_is_a_clear_error(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "x:y"\n')
    with pytest.raises(ValueError, match="bad.toml"):
        lmac_shm.Slab.create("lmac-pytest-bad", str(bad), 1, 0, 1)


def test_a_refused_ring_setting_is_its_own_error_class():
    """The env server reports a refused set-up (here a ring member that does not exist; also an
    iceoryx2 directory that is not this user's alone) in one line, by catching RefusedError."""
    assert issubclass(lmac_shm.RefusedError, ValueError)
    with pytest.raises(lmac_shm.RefusedError, match="does not exist in a ring of 2 members"):
        lmac_shm.Port("pytestrefused", "env", 5, 2, 2, 1.0)
