"""Recording: the rosbag2 MCAP bag the node writes, the log of record (``bag``: the format
and reading it back; ``recorder``: writing it while serving; ``recovery``: repairing what a
hard kill left). The state store beside the bags (people, ratings, the journal of accepted
feedback) is ``stars_ros.state``'s."""
from stars_ros.recording.bag import (METADATA_FILE, NODE_PLACEHOLDER, PID_FILE, STRING, STRING_HASH, MessageType,
                                     bag_files, bag_topics, default_folder, encode_string, is_finished, node_folder,
                                     qos_profile, read_decoded, read_messages)
from stars_ros.recording.recorder import Recorder
from stars_ros.recording.recovery import abandoned_bags, recover, salvage_messages

__all__ = ['METADATA_FILE', 'NODE_PLACEHOLDER', 'PID_FILE', 'STRING', 'STRING_HASH', 'MessageType',
           'Recorder', 'abandoned_bags', 'bag_files', 'bag_topics', 'default_folder',
           'encode_string', 'is_finished', 'node_folder', 'qos_profile', 'read_decoded', 'read_messages',
           'recover', 'salvage_messages']
