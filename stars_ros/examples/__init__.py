"""Example applications built on the package (not part of its API): ``demo``, the ranker serving two
people side by side (``python -m stars_ros.examples.demo``)."""
