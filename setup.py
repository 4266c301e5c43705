"""ament_python package fbg_accel_driver: driver, board simulator and calibration tools."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "fbg_accel_driver"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=["fbg_accel_driver", "fbg_accel_driver.*",
                                    "fbg_accel_calibration", "fbg_accel_calibration.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
    ],
    install_requires=["setuptools", "numpy", "pyserial", "PyYAML"],
    zip_safe=True,
    maintainer="fbg_accel_driver team",
    maintainer_email="fbg-accel@example.org",
    description="ROS 2 driver, simulator and thermal calibration for an FBG triaxial accelerometer",
    license="Apache-2.0",
    python_requires=">=3.10",
    entry_points={
        "console_scripts": [
            "driver = fbg_accel_driver.driver_node:main",
            "board_sim = fbg_accel_driver.sim.board_sim:main",
            "calibration = fbg_accel_calibration.calibration_node:main",
            "fbg-accel-calib = fbg_accel_calibration.cli:main",
        ],
    },
)
