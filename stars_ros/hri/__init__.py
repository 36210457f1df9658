"""The ROS4HRI (REP 155) bridge's logic without ROS: who is served, the scene from tracked
people, decisions the robot can act on and implicit outcomes (``docs/hri.md``)."""
