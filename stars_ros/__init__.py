"""StARS: socially appropriate robot actions ranked per user (ROS-free core)."""
__version__ = '0.1.0'
