"""The generated object dictionaries: up to date, loadable by canopen, and carrying every name the bench uses."""

from __future__ import annotations

import canopen
import pytest
from canopen.objectdictionary import ODVariable

from drivers.contract import extension, parameters
from drivers.contract.eds import read_eds
from drivers.contract.signals import SIGNAL_NAMES
from sim_backend import od_gen
from tests.canopen_helpers import REPO


@pytest.mark.parametrize("kind", ["pmsm", "spim"])
def test_eds_files_are_generated_and_complete(kind):
    path = REPO / "config" / "od" / f"drivebench-{kind}.eds"
    assert path.read_text() == od_gen.render(kind), "run: python -m sim_backend.od_gen"
    od = canopen.import_od(str(path), 1)
    assert od[0x100A].default == extension.FIRMWARE_VERSION
    assert od[0x1018][2].default == extension.PRODUCT_CODES[kind]
    assert read_eds(path).drivebench_kind == kind
    for i, name in enumerate(SIGNAL_NAMES):
        var = od[name]
        assert (var.index, var.data_type, var.pdo_mappable, var.writable) == (0x2010 + i, 0x8, True, False)
        assert od["scaled_" + name].factor > 0
    manufacturer = {v.name for v in od.values() if isinstance(v, ODVariable) and v.writable
                    and 0x2200 <= v.index < 0x2500}
    assert manufacturer == set(parameters.names_for(kind))
    assert [p.name for p in read_eds(path).offered_parameters()] == list(parameters.names_for(kind))
    assert od[0x2101].data_type == 0xF
    assert od[0x60FF].data_type == 0x4 and od[0x606C].data_type == 0x4      # INTEGER32, mrad/s
    assert od[0x1800][1].default == 0x181 and od[0x1A00][0].default == 3
