"""Recording: the rosbag2 MCAP bag the node writes, the log of record (``bag``: the format
and reading it back; ``recorder``: writing it while serving; ``recovery``: repairing what a
hard kill left), and the node's state store beside the bags (``state_store``: people,
ratings and the journal of accepted feedback; ``migration``: the files earlier versions
kept them in)."""
from stars_ros.recording.bag import (METADATA_FILE, NODE_PLACEHOLDER, PID_FILE, STRING, STRING_HASH, MessageType,
                                     bag_files, bag_topics, default_folder, encode_string, is_finished, node_folder,
                                     qos_profile, read_decoded, read_messages)
from stars_ros.recording.recorder import Recorder
from stars_ros.recording.recovery import abandoned_bags, recover, salvage_messages
from stars_ros.recording.state_store import DATABASE, StateStore, StoreLockedError, open_reader

__all__ = ['DATABASE', 'METADATA_FILE', 'NODE_PLACEHOLDER', 'PID_FILE', 'STRING', 'STRING_HASH', 'MessageType',
           'Recorder', 'StateStore', 'StoreLockedError', 'abandoned_bags', 'bag_files', 'bag_topics', 'default_folder',
           'encode_string', 'is_finished', 'node_folder', 'open_reader', 'qos_profile', 'read_decoded', 'read_messages',
           'recover', 'salvage_messages']
