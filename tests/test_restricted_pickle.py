"""The one restricted unpickler: only the allow-listed globals (or a hook's) are resolved."""

from __future__ import annotations

import collections
import io
import pickle

import pytest

from nmjax.data.restricted_pickle import RefusedGlobal, RestrictedUnpickler


class Stored:
    """A storage-like object pickled by a persistent id, as PyTorch pickles its storages."""

    def __init__(self, key: str):
        self.key = key


def pickle_with_ids(content) -> bytes:
    class Pickler(pickle.Pickler):
        def persistent_id(self, obj):
            return ("stored", obj.key) if isinstance(obj, Stored) else None

    buffer = io.BytesIO()
    Pickler(buffer, protocol=2).dump(content)
    return buffer.getvalue()


ORDERED = {("collections", "OrderedDict"): collections.OrderedDict}


def test_allowed_globals_are_resolved_and_plain_data_needs_none():
    content = collections.OrderedDict(a=[1, 2.5, "x"], b=(None, -7))
    for protocol in range(pickle.HIGHEST_PROTOCOL + 1):
        loaded = RestrictedUnpickler(pickle.dumps(content, protocol=protocol), ORDERED).load()
        assert loaded == content and type(loaded) is collections.OrderedDict
    assert RestrictedUnpickler(pickle.dumps({"n": [1, 2]}), {}).load() == {"n": [1, 2]}


def runs_a_command(marker) -> bytes:
    """A protocol-0 pickle that, unpickled unrestricted, calls os.system to touch `marker`."""
    return f"cos\nsystem\n(S'touch {marker}'\ntR.".encode()


def test_a_global_outside_the_allow_list_is_refused_before_it_runs(tmp_path):
    marker = tmp_path / "ran"
    with pytest.raises(RefusedGlobal) as err:
        RestrictedUnpickler(runs_a_command(marker), ORDERED).load()
    assert str(err.value) == "os.system"
    assert (err.value.module, err.value.name) == ("os", "system")
    assert isinstance(err.value, pickle.UnpicklingError)
    assert not marker.exists()
    # An allowed name resolves to what the table says, not to the real global.
    calls = RestrictedUnpickler(runs_a_command(marker), {("os", "system"): len}).load()
    assert calls == len(f"touch {marker}") and not marker.exists()
    # The real global, to show the pickle does what it says when nothing restricts it.
    assert pickle.loads(runs_a_command(marker)) == 0 and marker.exists()


def test_the_other_hook_resolves_a_family_of_names_and_refuses_with_none():
    data = pickle.dumps(collections.OrderedDict(x=1))
    asked = []

    def other(module, name):
        asked.append((module, name))
        return dict if module == "collections" else None

    assert RestrictedUnpickler(data, {}, other=other).load() == {"x": 1}
    assert asked == [("collections", "OrderedDict")]
    with pytest.raises(RefusedGlobal, match="collections.OrderedDict"):
        RestrictedUnpickler(data, {}, other=lambda module, name: None).load()


def test_persistent_ids_go_to_the_hook_and_are_refused_without_one():
    data = pickle_with_ids({"w": Stored("0"), "b": Stored("1"), "again": Stored("0")})
    seen = []

    def persistent_load(pid):
        seen.append(pid)
        return f"storage {pid[1]}"

    loaded = RestrictedUnpickler(data, {}, persistent_load=persistent_load).load()
    assert loaded == {"w": "storage 0", "b": "storage 1", "again": "storage 0"}
    assert sorted(seen) == [("stored", "0"), ("stored", "0"), ("stored", "1")]
    with pytest.raises(pickle.UnpicklingError, match="refused a persistent id"):
        RestrictedUnpickler(data, {}).load()


def test_latin1_reads_a_python2_byte_string():
    # Protocol 2 as Python 2 wrote it: a byte string as SHORT_BINSTRING, which Python 3 decodes.
    data = b"\x80\x02U\x03\xff\x00a."
    assert RestrictedUnpickler(data, {}, encoding="latin1").load() == "\xff\x00a"
    with pytest.raises(UnicodeDecodeError):
        RestrictedUnpickler(data, {}).load()
