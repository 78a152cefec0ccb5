"""deckland_interfaces: the .msg files, their documentation and units, the installed build, and
the correspondence with the pure cores' value types (so the nodes can switch field for field)."""

import dataclasses
import importlib
import json
from pathlib import Path
import re
import sys

from deckland.ros import msgtypes
import pytest

ROOT = Path(__file__).resolve().parents[2]
MSG_DIR = ROOT / 'src' / 'deckland_interfaces' / 'msg'
INSTALLED = Path(sys.prefix) / 'share' / 'deckland_interfaces' / 'msg'
MESSAGES = sorted(p.stem for p in MSG_DIR.glob('*.msg'))

#: unit suffixes of float fields (docs/interfaces.md rules) and the documented exceptions
UNIT_SUFFIXES = ('_m', '_m2', '_mps', '_mps2', '_s', '_hz', '_rad', '_radps', '_n')
DIMENSIONLESS = {'sigma',        # (14), m/s: the dataclass's name, unit in the comment
                 'gamma_bar'}    # (4), a gain


def blocks(name):
    """The .msg as paragraphs (lists of stripped lines, blank lines separate them)."""
    out, cur = [], []
    for line in (MSG_DIR / f'{name}.msg').read_text().splitlines():
        if line.strip():
            cur.append(line.strip())
        elif cur:
            out.append(cur)
            cur = []
    if cur:
        out.append(cur)
    return out


def fields(name):
    """(type, name) of every field (constants left out)."""
    out = []
    for block in blocks(name):
        for line in block:
            if line.startswith('#') or '=' in line:
                continue
            typ, fname = line.split()[:2]
            out.append((typ, fname))
    return out


#: where the value types live on main before the renovation moves them to the contract
_HOMES = {'ApronState': 'apron_estimator.types', 'VerticalState': 'apron_estimator.types',
          'PlannerOutput': 'landing_planner.types', 'Mode': 'landing_planner.types'}


def contract(name):
    """A value type from deckland_common.contract if present, else from its package."""
    try:
        mod = importlib.import_module('deckland_common.contract')
    except ImportError:
        mod = importlib.import_module(_HOMES[name])
    return getattr(mod, name)


def test_every_message_is_in_cmakelists_and_in_the_typestore():
    cmake = (ROOT / 'src' / 'deckland_interfaces' / 'CMakeLists.txt').read_text()
    listed = sorted(re.findall(r'"msg/(\w+)\.msg"', cmake))
    assert listed == MESSAGES
    assert msgtypes.register(msgtypes.typestore()) == [
        f'deckland_interfaces/msg/{m}' for m in MESSAGES]


@pytest.mark.parametrize('name', MESSAGES)
def test_every_field_is_documented_and_float_fields_carry_units(name):
    text = (MSG_DIR / f'{name}.msg').read_text()
    assert text.startswith('#'), f'{name}: no description at the top'
    for block in blocks(name):
        code = [ln for ln in block if not ln.startswith('#')]
        if code:
            assert any(ln.startswith('#') for ln in block), f'{name}: undocumented {code}'
    for typ, fname in fields(name):
        if typ.startswith(('float64', 'float32')):
            assert fname.endswith(UNIT_SUFFIXES) or fname in DIMENSIONLESS, \
                f'{name}.{fname}: no unit in the name'


@pytest.mark.parametrize('name', MESSAGES)
def test_installed_build_is_current_and_hashes_agree_with_rosidl(name):
    """`make setup` installed these very files, and rosbags computes the RIHS01 hash rosidl
    put in the type description (the hash bags and `ros2 bag` match types by)."""
    assert (INSTALLED / f'{name}.msg').read_text() == (MSG_DIR / f'{name}.msg').read_text()
    desc = json.loads((INSTALLED / f'{name}.json').read_text())
    rosidl = {h['type_name']: h['hash_string'] for h in desc['type_hashes']}
    store = msgtypes.typestore()
    full = f'deckland_interfaces/msg/{name}'
    assert store.hash_rihs01(full) == rosidl[full]
    for dep, h in rosidl.items():
        assert store.hash_rihs01(dep) == h, dep


def test_generated_classes_have_the_fields_of_the_files():
    mod = importlib.import_module('deckland_interfaces.msg')
    for name in MESSAGES:
        cls = getattr(mod, name)
        assert list(cls.get_fields_and_field_types()) == [f for _, f in fields(name)]


def _msg_fields(name):
    return {f for _, f in fields(name)}


def test_apron_state_carries_every_field_of_the_value_types():
    """The estimator's ApronState / VerticalState map field for field (renames listed)."""
    ApronState, VerticalState = contract('ApronState'), contract('VerticalState')
    renamed = {'t_s': 'header', 'camera_stamp_s': 'camera_stamp',
               'rel_position_var_m2': 'rel_position_cov_m2',
               'deck_rpy_rad': 'deck_orientation',
               'deck_yaw_rate_radps': 'deck_angular_velocity_radps'}
    msg = _msg_fields('ApronState')
    for f in dataclasses.fields(ApronState):
        assert renamed.get(f.name, f.name) in msg, f.name
    assert {f.name for f in dataclasses.fields(VerticalState)} == _msg_fields('VerticalState')


def test_planner_messages_carry_every_field_of_planner_output():
    PlannerOutput = contract('PlannerOutput')
    renamed = {'t_s': 'header', 'vertical_mode': 'vertical_frame'}
    both = _msg_fields('PlannerStatus') | _msg_fields('PlannerReference')
    for f in dataclasses.fields(PlannerOutput):
        assert renamed.get(f.name, f.name) in both, f.name
    assert 'precise_xy' in _msg_fields('PlannerReference')   # the property


def test_altitude_state_carries_the_controller_output_and_the_tracked_signals():
    from dob_altitude.types import AltitudeInput, AltitudeOutput
    msg = _msg_fields('AltitudeState')
    assert {f.name for f in dataclasses.fields(AltitudeOutput)} <= msg
    assert {'z_m', 'z_dot_mps', 'z_d_m', 'z_d_dot_mps'} <= msg
    assert {'z_m', 'z_dot_mps', 'z_d_m', 'z_d_dot_mps'} <= {
        f.name for f in dataclasses.fields(AltitudeInput)}


def test_mode_and_vertical_frame_constants_match_the_cores():
    from deckland_interfaces.msg import AltitudeState, PlannerReference, PlannerStatus
    Mode = contract('Mode')
    consts = {k: v for k, v in vars(PlannerStatus).items() if k.startswith('MODE_')}
    assert consts == {f'MODE_{m.name}': m.value for m in Mode}
    try:
        from deckland_common.contract import VERTICAL_FRAMES
    except ImportError:
        from landing_planner.types import VERTICAL_RELATIVE, VERTICAL_WORLD_RATE
        VERTICAL_FRAMES = (VERTICAL_RELATIVE, VERTICAL_WORLD_RATE)
    frames = {k: v for k, v in vars(PlannerReference).items() if k.startswith('VERTICAL_')}
    assert frames == {f'VERTICAL_{s.upper()}': i for i, s in enumerate(VERTICAL_FRAMES)}
    assert AltitudeState.CONTROLLER_DOB != AltitudeState.CONTROLLER_PID


def test_defaults_are_the_documented_unknowns():
    """A fresh message is 'nothing known': no source, invalid, identity attitude."""
    from deckland_interfaces.msg import ApronState, LinkStatus
    m = ApronState()
    assert m.source == ApronState.SOURCE_NONE and not m.tracked and not m.vertical.valid
    assert not m.deck_attitude_valid and m.deck_orientation.w == 1.0
    assert list(m.rivals) == [] and len(m.rel_position_cov_m2) == 4
    assert not LinkStatus().latency_valid


def test_msg_files_are_found_in_ament_prefixes_first_then_here_then_the_source(tmp_path):
    (tmp_path / 'empty').mkdir()
    own = tmp_path / 'prefix' / 'share' / 'deckland_interfaces' / 'msg'
    own.mkdir(parents=True)
    (own / 'Rival.msg').write_text((MSG_DIR / 'Rival.msg').read_text())
    env = {'AMENT_PREFIX_PATH': f'{tmp_path / "empty"}:{tmp_path / "prefix"}'}
    assert msgtypes.find_msg_dir(env) == own
    assert list(msgtypes.definitions(own)) == ['deckland_interfaces/msg/Rival']
    assert msgtypes.find_msg_dir({}) == INSTALLED               # this venv's build
    assert msgtypes.candidate_dirs({})[-1] == MSG_DIR           # the source tree last
    assert msgtypes.definitions(tmp_path / 'empty') == {}
    assert msgtypes.register(msgtypes.typestore(), tmp_path / 'empty') == []


def test_a_changed_definition_is_refused_not_silently_replaced(tmp_path):
    from rosbags.typesys import TypesysError
    (tmp_path / 'Rival.msg').write_text(
        (MSG_DIR / 'Rival.msg').read_text().replace('uint16 hits', 'uint32 hits'))
    with pytest.raises(TypesysError):
        msgtypes.register(msgtypes.typestore(), tmp_path)


def test_rivals_carry_the_trackers_hypotheses():
    """apron/state `rivals` from HorizontalTracker.rivals: offset, hits (confirmed at the
    tracker's rival_confirm_hits), the surface sampled under it, rejected, last seen."""
    from apron_estimator.horizontal import HorizontalParams, _Rival
    from deckland_common.messages import fill_rivals

    from deckland_interfaces.msg import ApronState, Rival

    confirm = HorizontalParams().rival_confirm_hits
    glint = _Rival(0.6, -0.1, 10.0)
    glint.hits, glint.surface, glint.rejected = confirm, -0.3, True   # on the ground: rejected
    flicker = _Rival(-0.2, 0.4, 11.5)
    msg = fill_rivals(ApronState(), [glint, flicker], 12.0, confirm, Rival)
    a, b = msg.rivals
    assert tuple(a.offset_m) == (0.6, -0.1) and a.hits == confirm and a.confirmed
    assert a.sampled and a.surface_level_m == -0.3 and a.rejected
    assert a.time_since_seen_s == pytest.approx(2.0)
    assert tuple(b.offset_m) == (-0.2, 0.4) and b.hits == 1 and not b.confirmed
    assert not b.sampled and b.surface_level_m == 0.0 and not b.rejected
    assert b.time_since_seen_s == pytest.approx(0.5)
    assert fill_rivals(msg, [], 13.0, confirm, Rival).rivals == []   # gone: cleared
