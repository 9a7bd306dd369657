"""``abh3 ros2 build-interface``: the ``abh3_can_interface`` package without colcon.

Two ways to the ROS 2 code generators: a sourced ROS 2 install (``AMENT_PREFIX_PATH``
holding ``rosidl_default_generators``), or the ROS 2 wheels from the Python package
registry installed into a cached virtual environment of their own
(``~/.cache/abh3-ros2/<distro>-<hash>``, keyed by the package list and the Python
version, so a second build installs nothing). Then plain ``cmake`` configures, builds and
installs the package into a prefix; two environment lines make it importable by rclpy.

The wheels' exported CMake files name the wheel builder's Python (``/opt/python/…``):
those paths are rewritten to the virtual environment's own once, after installing.

The tests use the same functions to get a real rclpy (``runtime=True`` adds rclpy, the RMW
and the message packages the bridge publishes). One of those, ``tf2_msgs`` (``/tf``), has
no wheel in the registry: a runtime environment builds it from its upstream definition
(ros2/geometry2's ``tf2_msgs/msg/TFMessage.msg``, the message alone) with the same cmake
steps, into the environment itself, so its Python imports it as the wheels' packages.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path

# the wheels' name prefix per distro: Kilted's are unprefixed (ros-rclpy), older ones not
PREFIX = {"kilted": "ros-", "jazzy": "ros-jazzy-"}
DISTROS = tuple(PREFIX)
RUNTIME = (
    "rclpy",
    "rmw-fastrtps-cpp",
    "std-msgs",
    "geometry-msgs",
    "nav-msgs",
    "diagnostic-msgs",
    "sensor-msgs",  # joint_states, joint_commands
)
GENERATORS = (
    "ament-cmake",
    "ament-cmake-ros",
    "ament-cmake-include-directories",
    "ament-package",
    "rosidl-default-generators",
    "rosidl-core-generators",
    "rosidl-cmake",
    "rosidl-adapter",
    "service-msgs",
)
# Kilted split ament_cmake_ros-core out; Jazzy's ament_cmake_ros insists on its test helpers
EXTRA = {
    "kilted": ("ament-cmake-ros-core",),
    "jazzy": (
        "ament-cmake-gmock",
        "ament-cmake-gtest",
        "ament-cmake-pytest",
        "python-cmake-module",
    ),
}
PLAIN = ("catkin-pkg", "numpy")  # not ROS packages: the same name in every distro
# the build machine of the wheels, named in their exported CMake files
WHEEL_PYTHON = "/opt/python/cp311-cp311"
PACKAGE = "abh3_can_interface"
# tf2_msgs has no wheel in the registry: its TFMessage (what /tf carries) built as above.
# The .msg is upstream's text to the byte (ros2/geometry2, tf2_msgs/msg/TFMessage.msg), so
# the type and its hash are ROS's; the package's other files (TF2Error, the services and
# the action) are left out: the bridge publishes only TFMessage
TF2_MSGS = "tf2_msgs"
TF2_FILES = {
    "msg/TFMessage.msg": "geometry_msgs/TransformStamped[] transforms\n",
    "CMakeLists.txt": (
        "cmake_minimum_required(VERSION 3.8)\n"
        "project(tf2_msgs)\n"
        "find_package(ament_cmake REQUIRED)\n"
        "find_package(rosidl_default_generators REQUIRED)\n"
        "find_package(builtin_interfaces REQUIRED)\n"
        "find_package(geometry_msgs REQUIRED)\n"
        "rosidl_generate_interfaces(${PROJECT_NAME}\n"
        '  "msg/TFMessage.msg"\n'
        "  DEPENDENCIES builtin_interfaces geometry_msgs\n"
        ")\n"
        "ament_package()\n"
    ),
    "package.xml": (
        '<?xml version="1.0"?>\n'
        '<package format="3">\n'
        "  <name>tf2_msgs</name>\n"
        "  <version>0.0.0</version>\n"
        "  <description>tf2_msgs/TFMessage only, built by abh3-supervisor's tests where the "
        "registry has no tf2_msgs wheel</description>\n"
        '  <maintainer email="dev@abh3-supervisor.invalid">abh3-supervisor</maintainer>\n'
        "  <license>BSD</license>\n"
        "  <buildtool_depend>ament_cmake</buildtool_depend>\n"
        "  <buildtool_depend>rosidl_default_generators</buildtool_depend>\n"
        "  <depend>builtin_interfaces</depend>\n"
        "  <depend>geometry_msgs</depend>\n"
        "  <exec_depend>rosidl_default_runtime</exec_depend>\n"
        "  <member_of_group>rosidl_interface_packages</member_of_group>\n"
        "  <export><build_type>ament_cmake</build_type></export>\n"
        "</package>\n"
    ),
}


class BuildError(RuntimeError):
    pass


def source_dir() -> Path:
    """The interface package shipped with the plugin (the vendor's .msg/.srv files)."""
    import abh3_plugins.ros2

    return Path(abh3_plugins.ros2.__file__).parent / "interface" / PACKAGE


def cache_root() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(os.environ.get("ABH3_ROS2_CACHE", str(Path(base) / "abh3-ros2")))


def packages(distro: str, runtime: bool, extra: Sequence[str] = ()) -> list[str]:
    """The registry names to install for ``distro``: the generators, and with ``runtime``
    rclpy, Fast DDS's RMW and the message packages the bridge uses."""
    if distro not in PREFIX:
        raise BuildError(f"unknown distro {distro!r} (known: {', '.join(DISTROS)})")
    ros = [*GENERATORS, *EXTRA[distro], *(RUNTIME if runtime else ())]
    return sorted({*(PREFIX[distro] + name for name in ros), *PLAIN, *extra})


def _key(distro: str, names: Sequence[str]) -> str:
    text = "\n".join([distro, f"{sys.version_info.major}.{sys.version_info.minor}", *names])
    return hashlib.sha256(text.encode()).hexdigest()[:12]


@contextlib.contextmanager
def _locked(path: Path) -> Iterator[None]:
    """One process at a time builds a given cache entry (two test runs, two users' shells)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def _run(cmd: Sequence[str], what: str, env: dict[str, str] | None = None) -> None:
    done = subprocess.run(list(cmd), env=env, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        tail = "\n".join((done.stdout + done.stderr).strip().splitlines()[-25:])
        raise BuildError(f"{what} failed (exit {done.returncode}): {' '.join(cmd)}\n{tail}")


def ensure_venv(
    distro: str, runtime: bool = False, extra: Sequence[str] = (), root: Path | None = None
) -> Path:
    """A virtual environment with the distro's wheels, made once and then reused."""
    names = packages(distro, runtime, extra)
    root = root or cache_root()
    venv = root / f"{distro}-{_key(distro, names)}"
    if (venv / ".complete").exists():
        return venv
    with _locked(root / f"{venv.name}.lock"):
        if (venv / ".complete").exists():  # another process made it while we waited
            return venv
        shutil.rmtree(venv, ignore_errors=True)  # a half-made one from an interrupted run
        _run([sys.executable, "-m", "venv", str(venv)], "creating the virtual environment")
        python = str(venv / "bin" / "python")
        _run(
            [python, "-m", "pip", "install", "-q", "--disable-pip-version-check", *names],
            f"installing the ROS 2 {distro} wheels from the package registry",
        )
        _fix_cmake_paths(venv)
        if runtime:
            build_tf2_msgs(venv)
        (venv / ".complete").write_text("\n".join(names) + "\n")
    return venv


def _fix_cmake_paths(venv: Path) -> None:
    """Point the wheels' CMake exports at this environment's Python headers and numpy."""
    python = str(venv / "bin" / "python")
    probe = (
        "import sysconfig, numpy; print(sysconfig.get_paths()['include']); "
        "print(numpy.get_include())"
    )
    out = subprocess.run([python, "-c", probe], capture_output=True, text=True, check=True)
    include, numpy_include = out.stdout.split()
    v = f"python{sys.version_info.major}.{sys.version_info.minor}"
    replace = [
        (f"{WHEEL_PYTHON}/include/{v}", include),
        (f"{WHEEL_PYTHON}/lib/{v}/site-packages/numpy/_core/include", numpy_include),
        (f"{WHEEL_PYTHON}/lib/{v}/site-packages/numpy/core/include", numpy_include),
    ]
    for file in (venv / "share").rglob("*.cmake"):
        text = file.read_text(errors="surrogateescape")
        if WHEEL_PYTHON not in text:
            continue
        for old, new in replace:
            text = text.replace(old, new)
        file.write_text(text, errors="surrogateescape")


def sourced_ros() -> Path | None:
    """The prefix of a sourced ROS 2 install that has the generators, or None."""
    for prefix in filter(None, os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep)):
        if (Path(prefix) / "share" / "rosidl_default_generators").is_dir():
            return Path(prefix)
    return None


def site_dir(prefix: Path, package: str = PACKAGE) -> Path:
    """Where the package's Python modules went under ``prefix``."""
    found = sorted(prefix.glob(f"lib*/python3*/*-packages/{package}"))
    if not found:
        raise BuildError(f"no {package} Python package under {prefix}/lib*/python3*/")
    return found[0].parent


def build_tf2_msgs(venv: Path) -> Path:
    """tf2_msgs (TFMessage) built with ``venv``'s generators and installed into ``venv``
    itself: its Python and libraries land where the wheels' are, found as theirs are."""
    with tempfile.TemporaryDirectory(prefix="abh3-tf2-msgs-") as tmp:
        source = Path(tmp) / TF2_MSGS
        for name, text in TF2_FILES.items():
            (source / name).parent.mkdir(parents=True, exist_ok=True)
            (source / name).write_text(text)
        return build(venv, venv, source, TF2_MSGS)


def build(
    prefix: Path, venv: Path | None = None, source: Path | None = None, package: str = PACKAGE
) -> Path:
    """Configure, build and install the interface (or ``source``, the package ``package``)
    into ``prefix`` with cmake; the generators come from ``venv`` (the wheels) or, without
    one, from the sourced ROS 2."""
    for tool in ("cmake", "make", "c++"):
        if shutil.which(tool) is None:
            raise BuildError(f"{tool} is not installed (apt-get install cmake make g++)")
    env = dict(os.environ)
    if venv is not None:
        python = venv / "bin" / "python"
        env["PATH"] = f"{venv / 'bin'}{os.pathsep}{env.get('PATH', '')}"
        env["AMENT_PREFIX_PATH"] = str(venv)
        env["CMAKE_PREFIX_PATH"] = str(venv)
    elif sourced_ros() is not None:
        python = Path(shutil.which("python3") or sys.executable)
    else:
        raise BuildError(
            "no ROS 2 generators: source a ROS 2 install, or give --distro to use the wheels"
        )
    prefix = prefix.resolve()
    with tempfile.TemporaryDirectory(prefix="abh3-interface-") as build_dir:
        _run(
            [
                "cmake",
                "-S",
                str(source or source_dir()),
                "-B",
                build_dir,
                f"-DCMAKE_INSTALL_PREFIX={prefix}",
                f"-DPython3_EXECUTABLE={python}",
                "-DBUILD_TESTING=OFF",
            ],
            "cmake configure",
            env,
        )
        jobs = str(max(1, min(4, os.cpu_count() or 1)))
        _run(["cmake", "--build", build_dir, "-j", jobs], "cmake build", env)
        _run(["cmake", "--install", build_dir], "cmake install", env)
    return site_dir(prefix, package)


def setup_lines(prefix: Path) -> list[str]:
    """The two lines that make the built package importable (rclpy finds it this way)."""
    site, lib = site_dir(prefix), prefix.resolve() / "lib"
    return [
        f'export PYTHONPATH="{site}${{PYTHONPATH:+:$PYTHONPATH}}"',
        f'export LD_LIBRARY_PATH="{lib}${{LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}}"',
    ]


def digest(source: Path | None = None) -> str:
    """A hash of the interface's files: a cached build is reused while they are unchanged."""
    h = hashlib.sha256()
    root = source or source_dir()
    for file in sorted(p for p in root.rglob("*") if p.is_file()):
        h.update(str(file.relative_to(root)).encode() + b"\0" + file.read_bytes())
    return h.hexdigest()[:12]


def cached_build(venv: Path) -> Path:
    """The interface built once per environment and interface content (for the tests)."""
    prefix = venv / f"{PACKAGE}-{digest()}"
    if (prefix / ".complete").exists():
        return prefix
    with _locked(venv.parent / f"{prefix.name}.{venv.name}.lock"):
        if not (prefix / ".complete").exists():
            shutil.rmtree(prefix, ignore_errors=True)
            build(prefix, venv)
            (prefix / ".complete").write_text("")
    return prefix


def command(prefix: Path, distro: str | None) -> int:
    """``abh3 ros2 build-interface``: build, then print the lines to source. From the
    registry's wheels it builds ``tf2_msgs`` (``/tf``) into the same prefix too: the
    registry has no wheel of it, and a sourced ROS 2 has its own."""
    venv = None
    if distro is not None or sourced_ros() is None:
        distro = distro or "kilted"
        print(f"abh3: the ROS 2 {distro} generators from the package registry…", file=sys.stderr)
        # with the runtime's wheels: geometry_msgs (what TFMessage is made of) needs the
        # RMW's type support to build against, which the generators alone lack
        venv = ensure_venv(distro, runtime=True)
    print(f"abh3: building {PACKAGE} into {prefix}…", file=sys.stderr)
    build(prefix, venv)
    built = PACKAGE
    if venv is not None:
        print(f"abh3: building {TF2_MSGS} (for /tf) into {prefix}…", file=sys.stderr)
        with tempfile.TemporaryDirectory(prefix="abh3-tf2-msgs-") as tmp:
            source = Path(tmp) / TF2_MSGS
            for name, text in TF2_FILES.items():
                (source / name).parent.mkdir(parents=True, exist_ok=True)
                (source / name).write_text(text)
            build(prefix, venv, source, TF2_MSGS)
        built = f"{PACKAGE} and {TF2_MSGS}"
    print(f"# {built} built; to use them with rclpy (transport: rclpy):", file=sys.stderr)
    for line in setup_lines(prefix):
        print(line)
    return 0
