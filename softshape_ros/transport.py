"""
The DDS transport of every softshape process: the package's Fast DDS profile, unless you chose.

Fast DDS reads its XML profiles once per process, when the first participant is created, from
``FASTRTPS_DEFAULT_PROFILES_FILE`` (or ``DEFAULT_FASTRTPS_PROFILES.xml`` in the working
directory). So :func:`configure_transport` must run before ``rclpy.init`` -- ``run_node`` does,
for every node, whether started by ``ros2 run``, ``ros2 launch`` or a test. No rclpy import here.

The user's choice wins and is never overridden: a profile of their own (checked, so that a
typo is an error at start instead of Fast DDS silently running on its defaults), an opt-out
(``SOFTSHAPE_TRANSPORT_PROFILE=none``), or another RMW.
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

PROFILE_ENV = 'FASTRTPS_DEFAULT_PROFILES_FILE'
#: Set to ``none`` to run on Fast DDS's defaults, or to a path to use another profile.
OVERRIDE_ENV = 'SOFTSHAPE_TRANSPORT_PROFILE'
FAST_DDS_RMWS = ('', 'rmw_fastrtps_cpp', 'rmw_fastrtps_dynamic_cpp')
PROFILE_NAME = 'fastdds.xml'


class TransportProfileError(RuntimeError):
    """A transport profile named by the user is missing, unreadable or not a Fast DDS profile."""


@dataclass(frozen=True)
class TransportChoice:
    """Which profile this process runs with (None = Fast DDS defaults) and why."""

    profile: Path | None
    reason: str


def package_profile() -> Path:
    """Return the shipped profile: the source tree's ``config/``, else the ament share dir."""
    src = Path(__file__).resolve().parents[1] / 'config' / PROFILE_NAME
    if src.is_file():
        return src
    try:
        from ament_index_python.packages import get_package_share_directory
        return Path(get_package_share_directory('softshape_ros')) / 'config' / PROFILE_NAME
    except Exception:  # not installed: report the source path (check_profile then says why)
        return src


def check_profile(path: str | os.PathLike, origin: str) -> Path:
    """
    Return ``path`` if it is a readable Fast DDS XML profile file.

    Otherwise raise TransportProfileError (missing, unreadable, not XML, or a root other than
    ``<dds>`` / ``<profiles>``), naming ``origin``: where the path came from.
    """
    p = Path(path)
    try:
        text = p.read_bytes()
    except OSError as exc:
        raise TransportProfileError(
            f'{origin}={p}: cannot read the Fast DDS profile: {exc.strerror or exc}') from None
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise TransportProfileError(f'{origin}={p}: not valid XML: {exc}') from None
    tag = root.tag.rsplit('}', 1)[-1]
    if tag not in ('dds', 'profiles'):
        raise TransportProfileError(
            f'{origin}={p}: not a Fast DDS profile (root element <{tag}>, expected <dds> or '
            '<profiles>)')
    return p


def configure_transport(environ=None) -> TransportChoice:
    """
    Point Fast DDS at the package profile unless the user chose otherwise; say which.

    ``environ`` (default ``os.environ``, which children started afterwards inherit) is read
    and updated. Returns the profile in use (None: Fast DDS's own defaults) and the reason;
    raises TransportProfileError if a profile named by the user, or the shipped one, is
    unusable.
    """
    env = os.environ if environ is None else environ
    rmw = env.get('RMW_IMPLEMENTATION', '')
    if rmw not in FAST_DDS_RMWS:
        return TransportChoice(None, f'RMW_IMPLEMENTATION={rmw}: not Fast DDS, left as it is')
    if env.get(PROFILE_ENV):
        return TransportChoice(check_profile(env[PROFILE_ENV], PROFILE_ENV), f'{PROFILE_ENV} set')
    if env.get('SKIP_DEFAULT_XML_FILE') == '1':
        return TransportChoice(None, 'SKIP_DEFAULT_XML_FILE=1: Fast DDS defaults')
    local = Path('DEFAULT_FASTRTPS_PROFILES.xml')
    if local.is_file():
        return TransportChoice(check_profile(local.resolve(), 'working directory'),
                               'DEFAULT_FASTRTPS_PROFILES.xml in the working directory')
    override = env.get(OVERRIDE_ENV, '')
    if override.lower() == 'none':
        return TransportChoice(None, f'{OVERRIDE_ENV}=none: Fast DDS defaults')
    if override:
        profile = check_profile(override, OVERRIDE_ENV)
        reason = f'{OVERRIDE_ENV} set'
    else:
        profile = check_profile(package_profile(), 'the shipped profile')
        reason = 'the package profile'
    env[PROFILE_ENV] = str(profile)
    return TransportChoice(profile, reason)
