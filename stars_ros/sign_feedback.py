"""Sign a feedback message for a ranker whose ``feedback_key_file`` is set; print the payload.

    python -m stars_ros.sign_feedback --key-file keys.txt \\
        '{"user_id": "alice", "scene_id": "s1", "action": "navigate", "score": 0.9}'

prints the message with its ``"auth"`` (stamped now, ROS time without simulated time), ready
for ``ros2 topic pub --once stars/feedback std_msgs/msg/String "{data: '...'}"``. With more
than one key in the file, ``--key-id`` says which signs. A program signs with
``stars_ros.feedback_auth.sign`` instead (docs/security.md). The message is checked against
msg_schemas/feedback.schema.json first, and its score against the rating scale of the
checkpoint the ranker serves (``--checkpoint``, default the packaged one): a score off it is
not signed.
"""
from __future__ import annotations

import argparse
import json
import sys
import time

from stars_ros import feedback_auth, messages
from stars_ros.errors import CheckpointError, ConfigError, OutOfScaleError
from stars_ros.model.checkpoint import read_checkpoint
from stars_ros.resources import DEFAULT_CHECKPOINT, resolve_checkpoint


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='python -m stars_ros.sign_feedback', description=__doc__.split('\n')[0])
    parser.add_argument('feedback', help='the feedback message as JSON, without "auth"')
    parser.add_argument('--key-file', required=True, help='file of KEY_ID:HEX_SECRET lines (the signer needs only '
                        'its own key)')
    parser.add_argument('--key-id', help='the key to sign with; needed when the file holds more than one')
    parser.add_argument('--stamp', type=int, help='signing time in ns of ROS time (default: now)')
    parser.add_argument('--checkpoint', default='', help='the checkpoint the ranker serves, whose rating scale the '
                        f'score must lie on (default: the packaged {DEFAULT_CHECKPOINT})')
    args = parser.parse_args(argv)
    try:
        keys = feedback_auth.load_keys(args.key_file)
    except ConfigError as error:
        parser.exit(2, f'error: {error}\n')
    if args.key_id is None and len(keys) > 1:
        parser.exit(2, f'error: {args.key_file} holds {len(keys)} keys ({", ".join(keys)}): say which with --key-id\n')
    key_id = args.key_id or next(iter(keys))
    if key_id not in keys:
        parser.exit(2, f"error: no key '{key_id}' in {args.key_file}\n")
    try:
        fields = json.loads(args.feedback)
    except ValueError as error:
        parser.exit(2, f'error: the feedback is not valid JSON: {error}\n')
    try:
        messages.check('feedback', fields)
    except messages.BadMessage as error:
        parser.exit(2, f'error: {error}\n')
    try:
        scale = read_checkpoint(resolve_checkpoint(args.checkpoint))['metadata'].get('rating_scale')
    except CheckpointError as error:
        parser.exit(2, f'error: {error}\n')
    stamp = time.time_ns() if args.stamp is None else args.stamp
    try:
        signed = feedback_auth.sign(fields, key_id, keys[key_id], stamp, scale)
    except OutOfScaleError as error:
        parser.exit(2, f'error: not signed: {error}\n')
    print(json.dumps(signed, separators=(',', ':')))
    return 0


if __name__ == '__main__':
    sys.exit(main())
