"""Every package.xml key resolves through rosdep: rosdistro's database or our rosdep/cgail.yaml.

On a full ROS 2 install, ``rosdep install --from-paths src --ignore-src`` (docs/rosdep.md) looks
up every dependency key of every package.xml under ``src``: a package of this workspace is
skipped, any other key must be a ROS package of the distribution or a rule of a registered
rosdep source, or the whole install fails. This test checks that offline:

* rosdistro's names are the snapshot ``rosdep/rosdistro_keys.txt`` (names only, with the
  repository, file and commit they were read from);
* the keys rosdistro lacks are ours, in ``rosdep/cgail.yaml``, which users register with rosdep;
  each of them is used by a package.xml, none shadows a rosdistro key, and every PyPI
  distribution it installs is pinned in ``requirements.txt``.

That each declared dependency is also imported by its package is test/test_package_deps.py's.
"""

from __future__ import annotations

from pathlib import Path
import re
from typing import Any
import xml.etree.ElementTree as ET

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
SNAPSHOT = ROOT / 'rosdep' / 'rosdistro_keys.txt'
OUR_RULES = ROOT / 'rosdep' / 'cgail.yaml'
#: The sections of the snapshot, each a rosdistro file the names were read from.
SNAPSHOT_SECTIONS = ('rosdep/python.yaml', 'jazzy/distribution.yaml')
#: Every package.xml (format 3) tag whose text is a rosdep key.
DEPENDENCY_TAGS = ('depend', 'build_depend', 'build_export_depend', 'buildtool_depend',
                   'buildtool_export_depend', 'exec_depend', 'test_depend', 'doc_depend')
KEY_PATTERN = re.compile(r'[A-Za-z0-9][A-Za-z0-9_.+-]*')
HINTS = {'ament_python': 'ament_python is a build type (the <export> <build_type>), not a '
                         'rosdep key: declare <buildtool_depend>python3-setuptools'
                         '</buildtool_depend> instead'}


def package_xmls(src: Path) -> list[Path]:
    """The package.xml files colcon finds under ``src``.

    Like colcon: not below a ``COLCON_IGNORE`` marker, not inside another package, and not in
    ``node_modules`` (the GUI's npm tree).
    """
    packages: list[Path] = []
    for path in sorted(src.rglob('package.xml'), key=lambda p: (len(p.parts), p)):
        folders = path.relative_to(src).parents
        if 'node_modules' in path.parts or any(
                (src / folder / 'COLCON_IGNORE').exists() for folder in folders):
            continue
        if any(path.parent.is_relative_to(known.parent) for known in packages):
            continue
        packages.append(path)
    return sorted(packages)


def dependency_keys(package_xml: Path) -> tuple[str, list[tuple[str, str]]]:
    """The package's name and its ``(tag, key)`` dependencies, in document order."""
    root = ET.parse(package_xml).getroot()
    name = (root.findtext('name') or '').strip()
    keys = [(element.tag, (element.text or '').strip()) for element in root
            if element.tag in DEPENDENCY_TAGS]
    return name, keys


def read_snapshot(path: Path) -> dict[str, set[str]]:
    """``{section: names}`` of the snapshot (``[section]`` lines, one name a line, ``#`` comments).

    Raises:
        ValueError: a name before the first section, or a line that is not a key name.
    """
    sections: dict[str, set[str]] = {}
    current: set[str] | None = None
    for number, raw in enumerate(path.read_text().splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith('#'):
            continue
        if line.startswith('[') and line.endswith(']'):
            current = sections.setdefault(line[1:-1], set())
        elif current is None:
            raise ValueError(f'{path.name}:{number}: expected a [section] line, found {line!r}')
        elif not KEY_PATTERN.fullmatch(line):
            raise ValueError(f'{path.name}:{number}: expected a key name, found {line!r}')
        else:
            current.add(line)
    return sections


def unresolvable_keys(src: Path, rosdistro: set[str], ours: set[str]) -> list[str]:
    """One line per package.xml key that rosdep could not resolve, naming package and key."""
    packages = {path: dependency_keys(path) for path in package_xmls(src)}
    workspace = {name for name, _ in packages.values()}
    problems = []
    for path, (_, keys) in packages.items():
        where = path.relative_to(src.parent)
        for tag, key in keys:
            if key in workspace or key in rosdistro or key in ours:
                continue
            hint = HINTS.get(key, 'check the key in ros/rosdistro, then add its name to '
                                  'rosdep/rosdistro_keys.txt, or add a rule to rosdep/cgail.yaml')
            problems.append(f'{where}: <{tag}>{key}</{tag}> is neither a package of this '
                            f'workspace nor a rosdistro key nor one of rosdep/cgail.yaml: {hint}')
    return problems


def pinned_distributions(requirements: Path) -> set[str]:
    """The normalised names of the distributions pinned in a requirements file."""
    return {re.split(r'[\s<>=!~;\[]', line, maxsplit=1)[0].lower().replace('_', '-')
            for line in requirements.read_text().splitlines()
            if line.strip() and not line.lstrip().startswith('#')}


def _installs(rule: Any) -> tuple[list[str], list[str]]:
    """``(apt packages, pip packages)`` of one OS's rule (a list, or ``{pip: {packages: []}}``)."""
    if isinstance(rule, list):
        return [str(p) for p in rule], []
    if isinstance(rule, dict) and set(rule) == {'pip'}:
        pip = rule['pip']
        packages = pip.get('packages') if isinstance(pip, dict) else pip
        if isinstance(packages, list):
            return [], [str(p) for p in packages]
    raise ValueError(f'expected [apt packages] or {{pip: {{packages: [...]}}}}, found {rule!r}')


def rule_problems(rules: dict[str, Any], rosdistro: set[str], used: set[str],
                  pinned: set[str]) -> list[str]:
    """One line per defect of our rosdep rules (``rosdep/cgail.yaml``, parsed)."""
    problems = []
    for key, by_os in sorted(rules.items()):
        if key in rosdistro:
            problems.append(f'{key}: rosdistro has this key; use it, remove our rule')
        if key not in used:
            problems.append(f'{key}: no package.xml uses it; remove it')
        if not isinstance(by_os, dict) or not {'debian', 'ubuntu'} <= set(by_os):
            problems.append(f'{key}: expected rules for debian and ubuntu (Jazzy\'s platforms), '
                            f'found {sorted(by_os) if isinstance(by_os, dict) else by_os!r}')
            continue
        for os_name, rule in sorted(by_os.items()):
            try:
                apt, pip = _installs(rule)
            except ValueError as error:
                problems.append(f'{key}: {os_name}: {error}')
                continue
            if key.endswith('-pip') and apt:
                problems.append(f'{key}: {os_name}: a -pip key installs with pip only, found '
                                f'{apt}')
            if not key.endswith('-pip') and os_name in ('debian', 'ubuntu') and apt != [key]:
                problems.append(f'{key}: {os_name}: expected the Debian package [{key}], found '
                                f'{apt or pip}')
            problems.extend(f'{key}: {os_name}: pip installs {name!r}, which requirements.txt '
                            'does not pin' for name in pip
                            if name.lower().replace('_', '-') not in pinned)
    return problems


def _rosdistro_names() -> set[str]:
    return set().union(*read_snapshot(SNAPSHOT).values())


def _our_rules() -> dict[str, Any]:
    rules = yaml.safe_load(OUR_RULES.read_text())
    assert isinstance(rules, dict), f'{OUR_RULES.name}: expected a mapping of keys to rules'
    return rules


def test_every_package_xml_key_resolves_through_rosdistro_or_our_rules() -> None:
    problems = unresolvable_keys(ROOT / 'src', _rosdistro_names(), set(_our_rules()))
    assert not problems, '\n' + '\n'.join(problems)


def test_our_rules_are_used_needed_and_pinned() -> None:
    used = {key for path in package_xmls(ROOT / 'src') for _, key in dependency_keys(path)[1]}
    problems = rule_problems(_our_rules(), _rosdistro_names(), used,
                             pinned_distributions(ROOT / 'requirements.txt'))
    assert not problems, '\n' + '\n'.join(problems)


def test_snapshot_holds_both_files_and_the_keys_we_rely_on() -> None:
    sections = read_snapshot(SNAPSHOT)
    assert sorted(sections) == sorted(SNAPSHOT_SECTIONS)
    python_keys, jazzy = sections['rosdep/python.yaml'], sections['jazzy/distribution.yaml']
    # the whole of python.yaml (a truncated copy would silently reject valid keys)
    assert len(python_keys) > 1200
    assert {'python3-numpy', 'python3-trimesh-pip', 'python3-cantools-pip', 'python3-torch',
            'yapf', 'zulip-pip'} <= python_keys
    assert {'rclpy', 'std_msgs', 'lifecycle_msgs', 'tf2_msgs', 'ament_index_python'} <= jazzy
    # names rosdistro does not have (the reason rosdep/cgail.yaml exists)
    assert not {'ament_python', 'python3-trimesh', 'python3-cantools', 'python3-onnx'} & (
        python_keys | jazzy)


def _write_package(folder: Path, name: str, dependencies: str) -> None:
    folder.mkdir(parents=True)
    (folder / 'package.xml').write_text(
        f'<?xml version="1.0"?>\n<package format="3">\n  <name>{name}</name>\n'
        f'{dependencies}\n  <export><build_type>ament_python</build_type></export>\n</package>\n')


def test_checker_names_package_and_key_of_each_unresolvable_key(tmp_path: Path) -> None:
    src = tmp_path / 'src'
    _write_package(src / 'alpha', 'alpha', '  <buildtool_depend>ament_python</buildtool_depend>\n'
                   '  <exec_depend>rclpy</exec_depend>\n  <exec_depend>beta</exec_depend>\n'
                   '  <exec_depend>python3-ours</exec_depend>\n'
                   '  <test_depend>python3-no-such-module</test_depend>')
    _write_package(src / 'group' / 'beta', 'beta', '  <depend>python3-numpy</depend>')
    # not packages colcon would find: ignored, and inside another package
    _write_package(src / 'ignored' / 'gamma', 'gamma', '  <depend>python3-bogus</depend>')
    (src / 'ignored' / 'COLCON_IGNORE').touch()
    _write_package(src / 'alpha' / 'vendored', 'delta', '  <depend>python3-bogus</depend>')

    assert [p.relative_to(src).as_posix() for p in package_xmls(src)] == [
        'alpha/package.xml', 'group/beta/package.xml']
    assert unresolvable_keys(src, {'rclpy', 'python3-numpy'}, {'python3-ours'}) == [
        'src/alpha/package.xml: <buildtool_depend>ament_python</buildtool_depend> is neither a '
        'package of this workspace nor a rosdistro key nor one of rosdep/cgail.yaml: '
        + HINTS['ament_python'],
        'src/alpha/package.xml: <test_depend>python3-no-such-module</test_depend> is neither a '
        'package of this workspace nor a rosdistro key nor one of rosdep/cgail.yaml: check the '
        'key in ros/rosdistro, then add its name to rosdep/rosdistro_keys.txt, or add a rule to '
        'rosdep/cgail.yaml']


def test_snapshot_reader_rejects_a_name_outside_a_section_and_a_bad_name(tmp_path: Path) -> None:
    snapshot = tmp_path / 'keys.txt'
    snapshot.write_text('# header\n[rosdep/python.yaml]\npython3-numpy\n\n[other]\nrclpy\n')
    assert read_snapshot(snapshot) == {'rosdep/python.yaml': {'python3-numpy'},
                                       'other': {'rclpy'}}
    snapshot.write_text('python3-numpy\n')
    with pytest.raises(ValueError, match=r"keys\.txt:1: expected a \[section\] line, found "
                                         r"'python3-numpy'"):
        read_snapshot(snapshot)
    snapshot.write_text('[s]\npython3-numpy: {debian: [x]}\n')
    with pytest.raises(ValueError, match=r'keys\.txt:2: expected a key name'):
        read_snapshot(snapshot)


def test_rule_checker_reports_each_defect() -> None:
    pip = {'pip': {'packages': ['left-pad']}}
    rules = {
        'python3-good-pip': {'debian': {'pip': {'packages': ['Good_Dist']}}, 'ubuntu': pip},
        'python3-numpy': {'debian': ['python3-numpy'], 'ubuntu': ['python3-numpy']},
        'python3-apt-pip': {'debian': ['python3-apt'], 'ubuntu': pip},
        'python3-onnx': {'debian': ['python3-onnx'], 'ubuntu': ['onnx'], 'osx': 'brew onnx'},
        'python3-debian-only': {'debian': ['python3-debian-only']},
    }
    used = {'python3-good-pip', 'python3-numpy', 'python3-apt-pip', 'python3-onnx'}
    assert rule_problems(rules, {'python3-numpy'}, used, {'good-dist'}) == [
        "python3-apt-pip: debian: a -pip key installs with pip only, found ['python3-apt']",
        "python3-apt-pip: ubuntu: pip installs 'left-pad', which requirements.txt does not pin",
        'python3-debian-only: no package.xml uses it; remove it',
        "python3-debian-only: expected rules for debian and ubuntu (Jazzy's platforms), found "
        "['debian']",
        'python3-good-pip: ubuntu: pip installs \'left-pad\', which requirements.txt does not pin',
        'python3-numpy: rosdistro has this key; use it, remove our rule',
        "python3-onnx: osx: expected [apt packages] or {pip: {packages: [...]}}, found 'brew "
        "onnx'",
        "python3-onnx: ubuntu: expected the Debian package [python3-onnx], found ['onnx']",
    ]
    assert rule_problems({'python3-good-pip': rules['python3-good-pip']}, set(),
                         {'python3-good-pip'}, {'good-dist', 'left-pad'}) == []
