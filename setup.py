"""ament_python package fbg_accel_driver: driver, board simulator and calibration tools."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "fbg_accel_driver"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=["fbg_accel_driver", "fbg_accel_driver.*",
                                    "fbg_accel_calibration", "fbg_accel_calibration.*",
                                    "fbg_accel_sim", "fbg_accel_sim.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
    ],
    # Every third-party module the code imports (test/test_bringup.py checks this against an import scan;
    # exact pins for the venv are in requirements.txt). ROS packages (rclpy, message packages, launch)
    # come from the ROS install or the ros-jazzy-* wheels and are declared in package.xml only.
    install_requires=[
        "setuptools",
        "numpy",
        "pyserial",
        "PyYAML",
        "mcap",
        "mcap-ros2-support",
        "zstandard",
        "scipy",  # calibration fit, detector, diagnosis; the driver only for a declared correction term
        "matplotlib",  # reports and plots (fbg-accel-calib); never imported by the driver
        "AllanTools",
        "tqdm",  # progress bars of fbg-accel-calib; never imported by the driver
    ],
    zip_safe=True,
    maintainer="fbg_accel_driver team",
    maintainer_email="fbg-accel@example.org",
    description="ROS 2 driver, simulator and thermal calibration for an FBG triaxial accelerometer",
    license="Apache-2.0",
    python_requires=">=3.10",
    entry_points={
        "console_scripts": [
            "driver = fbg_accel_driver.driver_main:main",
            "board_sim = fbg_accel_sim.board_sim_main:main",
            "calibration = fbg_accel_calibration.recorder.calibration_main:main",
            "fbg-accel-calib = fbg_accel_calibration.commands.cli_main:main",
        ],
    },
)
