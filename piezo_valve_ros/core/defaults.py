"""The package's defaults, each in one place (SI units).

ROS-free; the nodes' parameter declarations, the tools and the core read them from here.
"""
__all__ = ["CONTROL_PERIOD_S", "PAPER_CONTROL_PERIOD_S", "BAG_STORAGE"]

CONTROL_PERIOD_S = 1e-3        # a rig's control period [s]: the nodes', the tools' and the backend checks' default
PAPER_CONTROL_PERIOD_S = 1e-4  # the paper's 10 kHz loop [s]: the core's simulations and Table 1's gains
BAG_STORAGE = "mcap"           # the storage plugin bags are written with unless told otherwise (io.bags.STORAGES)
