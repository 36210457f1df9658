"""Fleet intake: the ranker taking in its peers' stars/user_model messages (fleet sharing).
ROS-free; ``RankerCore.accept_user_model`` hands each message here.

A peer's model brings the ratings it was solved from; those this node lacks join the
user's (``Personalisation.add_peer_ratings``). A message solved against another checkpoint
is ignored, and a peer folding in with another λ is warned about, each once per peer and
value, so that a misconfigured fleet is reported without flooding stars/errors.
"""
from __future__ import annotations

from typing import Callable

from stars_ros import messages
from stars_ros.errors import StarsError

MAX_PEERS_REMEMBERED = 10000


class FleetIntake:
    """Checks and takes in peers' user models.

    Args:
        params (dict): the node's parameters (``fold_in_regularisation``, ``max_message_bytes``), read at each use.
        topic (str): stars/user_model's resolved name, for the reports.
        report (callable): ``report(kind, detail, topic)``, the node's problem report.
    """

    def __init__(self, params: dict, topic: str, report: Callable):
        self.params, self.topic, self.report = params, topic, report
        self._peers_reported = set()  # (peer, fingerprint or λ) warned about once
        self.may_store = lambda user_id: True  # store_policy: whose models may be taken in (node.consent)

    def accept(self, text: str, personalisation) -> bool:
        """Take in a peer's stars/user_model message for ``personalisation`` (the owner of
        people): the ratings it was solved from that this node lacks join the user's.
        True when the user now waits to be re-solved. A message of another checkpoint is
        ignored (warned about once per peer and checkpoint); a bad one is reported and
        changes nothing."""
        topic, predictor = self.topic, personalisation.predictor
        try:
            payload = messages.parse_user_model(text, self.params['max_message_bytes'])
        except messages.BadMessage as error:
            self.report(error.kind, f'peer user model refused: {error}', topic)
            return False
        peer, user_id = payload.get('origin', 'a ranker without fleet sharing'), payload['user_id']
        if personalisation.is_forgotten(user_id):  # the report does not name them: stars/errors is recorded
            self.report('forgotten', f'a user model from {peer} of a person forgotten here: refused, nothing taken in',
                        topic)
            return False
        if not self.may_store(user_id):
            self.report('consent', f'a user model from {peer} of a person not on the consent list (store_policy '
                        'consented): refused, nothing taken in', topic)
            return False
        if payload['fingerprint'] != predictor.fingerprint:
            self._warn_once(peer, payload['fingerprint'], f"user models from {peer} were solved against checkpoint "
                            f"{payload['fingerprint'][:12]}, not the served {predictor.fingerprint[:12]}: "
                            'ignored (reported once per peer and checkpoint)')
            return False
        if payload['regularisation'] != self.params['fold_in_regularisation']:
            self._warn_once(peer, payload['regularisation'], f"{peer} folds in with fold_in_regularisation = "
                            f"{payload['regularisation']}, this node with {self.params['fold_in_regularisation']}: "
                            'their models of a user differ (reported once per peer and value)')
        try:
            return personalisation.add_peer_ratings(user_id, payload.get('ratings', []), peer)
        except StarsError as error:
            self.report(messages.error_kind(error), f"user model of '{user_id}' from {peer} refused, nothing taken in: "
                        f'{error}', topic)
            return False

    def _warn_once(self, peer: str, value, detail: str):
        if (peer, value) not in self._peers_reported:
            if len(self._peers_reported) >= MAX_PEERS_REMEMBERED:
                self._peers_reported.clear()
            self._peers_reported.add((peer, value))
            self.report('fleet', detail, self.topic)
