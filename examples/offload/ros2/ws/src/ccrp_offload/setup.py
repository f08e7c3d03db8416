from setuptools import setup

package_name = "ccrp_offload"

setup(
    name=package_name,
    version="1.0.0",
    packages=[package_name],
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="ccrp",
    maintainer_email="ccrp@example.org",
    description="ccrp's offloading example: laser scans to an occupancy grid on the clone",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "scan_to_map = ccrp_offload.scan_to_map:main",
            "map_stats = ccrp_offload.map_stats:main",
        ],
    },
)
