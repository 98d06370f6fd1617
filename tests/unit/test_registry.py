"""The service registry against the schema and the code it names."""

from __future__ import annotations

import pytest

from swarmrec.errors import ConfigError
from swarmrec.runtime.runner import ServiceBase
from swarmrec.runtime.settings import BusSettings, StorageSettings
from swarmrec.services import contracts, registry
from swarmrec.wire import messages as pb


def test_every_kind_of_the_schema_has_one_entry_and_every_entry_its_own_enum_value() -> None:
    schema = {name: value for name, value in pb.ServiceKind.items() if value != 0}
    builtin = {k: e for k, e in registry.REGISTRY.items() if e.factory.startswith("swarmrec.")}
    assert {f"SERVICE_KIND_{k.upper().replace('-', '_')}": e.wire for k, e in builtin.items()} == schema


@pytest.mark.parametrize("kind", list(registry.REGISTRY))
def test_each_entry_names_a_service_class_and_settings_bus_first(kind: str) -> None:
    entry = registry.spec(kind)
    cls = entry.load()
    assert issubclass(cls, ServiceBase)
    assert entry.all_components[0] is BusSettings
    if entry.stateful:
        assert StorageSettings in entry.all_components
    names = [ep.name for ep in cls.ENDPOINTS] + [s.name for s in cls.SUBSCRIPTIONS]
    assert len(names) == len(set(names)) and "info" not in names  # info is the runner's
    if entry.metrics is not None:
        assert entry.metrics.describe()


def test_an_unknown_kind_is_named_with_the_known_ones() -> None:
    with pytest.raises(ConfigError, match=r"unknown service 'shard'; services: router, detector"):
        registry.spec("shard")


def test_a_kind_or_a_wire_value_cannot_be_registered_twice() -> None:
    shard = registry.spec("index-shard")
    with pytest.raises(ValueError, match="already registered"):
        registry.register(shard)
    with pytest.raises(ValueError, match="wire value 3"):
        registry.register(registry.ServiceSpec("other", shard.wire, shard.factory, "x"))


def test_workloads_name_only_per_robot_kinds() -> None:
    for kinds in registry.WORKLOADS.values():
        assert all(registry.spec(k).scope == "robot" for k in kinds)


def test_the_contract_pages_under_services_are_current() -> None:
    # Regenerated and compared: `python -m swarmrec.services.contracts` rewrites them.
    assert contracts.main(["--check"]) == 0


def test_a_shards_help_lists_its_own_settings_and_nothing_of_cameras_or_fusion() -> None:
    page = contracts.render_kind(registry.spec("index-shard"))
    assert "--label-bounds" in page and "--data-dir" in page
    assert "--camera-fx" not in page and "--fusion-law" not in page
    assert "swarmrec_shard_partial_queries_total" in page and "swarmrec_fusion" not in page
