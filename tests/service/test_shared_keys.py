"""API keys with a shared engine: several API processes on one store see each other's
keys at once (made, revoked, or gone with their map), on SQLite and PostgreSQL."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from service.maps import MapService
from service.settings import Settings
from service.store import MapRecord
from tests.support.clusters import PrivatePostgres


@pytest.fixture(params=["sqlite", "postgresql"])
def two_api_processes(
    request: pytest.FixtureRequest, tmp_path: Path
) -> Iterator[tuple[MapService, MapService]]:
    """Two MapServices on one store whose engine says it is shared (as the ray engine's);
    their engines are never started (key handling runs in the API process only)."""
    if request.param == "sqlite":
        url = str(tmp_path / "store")
    else:
        server: PrivatePostgres = request.getfixturevalue("postgres")
        url = server.new_database()
    settings = Settings(data_dir=tmp_path / "unused", store={"url": url})
    first = MapService(settings)
    catalog = first.store.catalog()
    catalog.add(MapRecord("m1", "one", "mapping", {}, time.time()))
    catalog.close()
    second = MapService(settings)
    for service in (first, second):
        service.pool.shared = True
    yield first, second
    for service in (first, second):
        service._catalog.close()
        service.store.close()


def test_a_key_made_or_revoked_in_one_api_process_counts_in_the_other(
    two_api_processes: tuple[MapService, MapService],
) -> None:
    first, second = two_api_processes
    key, secret = first.create_key("m1", "write")
    found = second.find_key(secret)
    assert found == key and second.key_alive(key)
    assert [k.id for k in second.keys("m1")] == [key.id]
    second.delete_key("m1", key.id)
    assert first.find_key(secret) is None and not first.key_alive(key)
    assert first.keys("m1") == []


def test_a_deleted_maps_keys_are_gone_for_every_api_process(
    two_api_processes: tuple[MapService, MapService],
) -> None:
    first, second = two_api_processes
    key, secret = first.create_key("m1", "read")
    assert second.find_key(secret) == key
    first._catalog.remove("m1")  # what first.delete does to the catalogue
    assert second.find_key(secret) is None and not second.key_alive(key)
