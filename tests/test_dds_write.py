"""The bridge's flat DDS messages written in one pack (plugins/abh3_plugins/ros2/dds_write.py):
the same bytes cyclonedds's own ``write`` hands the middleware, and a reader decodes them."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from typing import Any

import pytest

pytest.importorskip("cyclonedds")
from cyclonedds.domain import DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration

from abh3_plugins.ros2 import dds_write, types
from abh3_plugins.ros2.dds import LOOPBACK_URI, qos
from abh3_plugins.ros2.settings import QosSettings

DOMAIN = 91  # no other test's
FLAT = [types.Abh3Velocity, types.Abh3Current, types.Abh3Input]
FLAT += [getattr(types, f"Abh3Brd{n}") for n in range(7)]


@pytest.fixture
def participant(monkeypatch: pytest.MonkeyPatch) -> Iterator[DomainParticipant]:
    monkeypatch.setenv("CYCLONEDDS_URI", LOOPBACK_URI)  # loopback only, multicast off
    yield DomainParticipant(DOMAIN)


def _sample(typ: type, base: float) -> Any:
    """Distinct values of each field's kind, some negative (int32's sign, float64's)."""
    values = {}
    for i, field in enumerate(dataclasses.fields(typ)):
        value = (-1) ** i * (base + i)
        values[field.name] = value + 0.25 if "float" in str(field.type) else int(value)
    return typ(**values)


@pytest.mark.parametrize("typ", FLAT, ids=lambda t: t.__name__)
def test_a_flat_message_is_the_bytes_of_the_idl_and_a_reader_decodes_it(
    participant: DomainParticipant, typ: type, monkeypatch: pytest.MonkeyPatch
) -> None:
    topic: Topic[Any] = Topic(participant, f"rt/dds_write/{typ.__name__}", typ)
    ros = qos(QosSettings())
    reader = DataReader(participant, topic, qos=ros)
    writer = DataWriter(participant, topic, qos=ros)
    publish = dds_write.packed_write(writer, typ)
    assert publish != writer.write  # the one-pack path was taken
    handed: list[bytes] = []
    real = dds_write.ddspy_write  # type: ignore[attr-defined]

    def spy(ref: Any, data: bytes) -> int:
        handed.append(data)
        return int(real(ref, data))

    monkeypatch.setattr(dds_write, "ddspy_write", spy)
    publish = dds_write.packed_write(writer, typ)  # made again: it binds the write
    samples = [_sample(typ, 1000.0 * k + 7) for k in (1, 2, 3)]
    for sample in samples:
        publish(sample)
    # what cyclonedds's own write would have handed the middleware, byte for byte
    assert handed == [dds_write._serialised(writer, s) for s in samples]
    got = []
    for sample in reader.take_iter(timeout=duration(seconds=10)):  # ends at a 10 s silence
        got.append(sample)
        if len(got) == len(samples):
            break
    assert got == samples


def _writer(participant: DomainParticipant, name: str, typ: type) -> DataWriter[Any]:
    topic: Topic[Any] = Topic(participant, f"rt/dds_write/{name}", typ)
    return DataWriter(participant, topic, qos=qos(QosSettings()))


def test_a_message_with_strings_or_of_another_kind_keeps_the_idls_write(
    participant: DomainParticipant,
) -> None:
    for typ in (types.KeyValue, types.Header, types.Odometry):
        writer = _writer(participant, typ.__name__, typ)
        assert dds_write.packed_write(writer, typ) == writer.write


def test_a_wrong_sample_is_refused_as_cyclonedds_refuses_it(
    participant: DomainParticipant,
) -> None:
    publish = dds_write.packed_write(
        _writer(participant, "wrong", types.Abh3Velocity), types.Abh3Velocity
    )
    with pytest.raises(TypeError):
        publish(types.Abh3Brd0(1, 2))


def test_a_value_out_of_its_fields_range_is_refused_as_cyclonedds_refuses_it(
    participant: DomainParticipant,
) -> None:
    writer = _writer(participant, "range", types.Abh3Brd0)
    publish = dds_write.packed_write(writer, types.Abh3Brd0)
    with pytest.raises(Exception, match="error") as raised:  # cyclonedds names the member
        publish(types.Abh3Brd0(error=1 << 40, alarm=0))
    with pytest.raises(type(raised.value)):
        writer.write(types.Abh3Brd0(error=1 << 40, alarm=0))
