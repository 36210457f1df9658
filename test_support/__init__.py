"""What the tests and the benchmarks share, kept out of the installed package: real nodes on
loopback DDS in reserved ROS domains (``loopback``) and the generated SocNav1-format data set
(``synthetic_socnav``). Imported from the checkout's root (pytest.ini's pythonpath; the
benchmarks put the checkout on sys.path)."""
