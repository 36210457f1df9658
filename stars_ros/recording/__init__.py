"""Recording: the rosbag2 MCAP bag the node writes (the log of record), its feedback journal,
recovery of an interrupted bag, and reading bags back."""
from stars_ros.recording.bag import (JOURNAL, METADATA_FILE, PID_FILE, STRING, STRING_HASH, Recorder, abandoned_bags,
                                     bag_topics, default_folder, encode_string, is_finished, qos_profile,
                                     read_messages, recover)

__all__ = ['JOURNAL', 'METADATA_FILE', 'PID_FILE', 'STRING', 'STRING_HASH', 'Recorder', 'abandoned_bags', 'bag_topics',
           'default_folder', 'encode_string', 'is_finished', 'qos_profile', 'read_messages', 'recover']
