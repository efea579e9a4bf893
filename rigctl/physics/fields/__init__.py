"""Field models of electromagnet rigs behind one interface (`FieldModel`): today's loops
(`LoopModel`) and the multipole electromagnet model (`MPEM`) of mag_manip's calibration files;
allocation of currents for any number of coils (`allocate`) and the MPEM fit from Hall-probe
samples (`fit`)."""

from rigctl.physics.fields.loops import LoopModel
from rigctl.physics.fields.model import GRADIENT_TERMS, U_COMPONENTS, FieldModel
from rigctl.physics.fields.mpem import MPEM, Source
from rigctl.physics.fields.mpem_file import (
    load_field_model,
    load_mpem,
    mpem_to_yaml,
    parse_mpem,
    write_mpem,
)

__all__ = ["FieldModel", "GRADIENT_TERMS", "LoopModel", "MPEM", "Source", "U_COMPONENTS",
           "load_field_model", "load_mpem", "mpem_to_yaml", "parse_mpem", "write_mpem"]
