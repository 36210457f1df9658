"""The ranker's SROS2 policy (config/security/ranker.policy.xml, docs/security.md) with
sros2's own tools: it follows sros2's policy schema, a keystore, the ranker's enclave and its
signed permissions are made from it, and the permissions XML follows the DDS permissions
schema sros2 ships and grants exactly the ranker's inputs and outputs, everything else denied.
test_feedback_auth_node.py checks the same topic lists against a running ranker. sros2 comes
with a ROS install (ros-jazzy-sros2); no registry here serves it, so these tests skip where it
cannot be imported. The PyPI Fast DDS cannot enforce the result."""
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
POLICY = REPO / 'config' / 'security' / 'ranker.policy.xml'
ENCLAVE = '/stars_ros/ranker'
SUBSCRIBES = {'stars/scene', 'stars/user_id', 'stars/feedback', 'stars/question_request', 'stars/user_model',
              'stars/typed/feedback'}
PUBLISHES = {'stars/ranking', 'stars/errors', 'stars/question', 'stars/user_model', 'stars/markers', 'diagnostics',
             'rosout', 'parameter_events'}
SERVES = {'reload', 'rank_actions', 'rank_candidates', 'choose_question', 'describe_parameters',
          'get_parameter_types', 'get_parameters', 'get_type_description', 'list_parameters', 'set_parameters',
          'set_parameters_atomically'}


@pytest.fixture
def sros2(monkeypatch):
    """sros2's modules; it finds its share files through the ament index of the venv."""
    monkeypatch.setenv('AMENT_PREFIX_PATH', sys.prefix)
    monkeypatch.setenv('ROS_DOMAIN_ID', '0')
    pytest.importorskip('sros2', reason='sros2 comes with a ROS install (ros-jazzy-sros2); no registry here serves it')
    from lxml import etree
    from sros2 import policy
    from sros2.keystore import _enclave, _keystore, _permission
    return etree, policy, _keystore, _enclave, _permission


def test_the_policy_gives_signed_permissions_that_follow_the_schema_and_grant_only_the_ranker_topics(sros2, tmp_path):
    etree, policy, keystore, enclave, permission = sros2
    policy.load_policy(POLICY)  # validates against sros2's policy.xsd
    store = tmp_path / 'keystore'
    keystore.create_keystore(store)
    enclave.create_enclave(store, ENCLAVE)
    permission.create_permission(store, ENCLAVE, POLICY)
    folder = store / 'enclaves' / ENCLAVE.lstrip('/')
    assert {'cert.pem', 'key.pem', 'permissions.xml', 'permissions.p7s', 'governance.p7s'} <= {
        p.name for p in folder.iterdir()}
    schema = etree.XMLSchema(etree.parse(str(policy.get_transport_schema('dds', 'permissions.xsd'))))
    permissions = etree.parse(str(folder / 'permissions.xml'))
    schema.assertValid(permissions)
    etree.XMLSchema(etree.parse(str(policy.get_transport_schema('dds', 'governance.xsd')))).assertValid(
        etree.parse(str(store / 'enclaves' / 'governance.xml')))
    [grant] = permissions.findall('permissions/grant')
    assert grant.findtext('subject_name') == f'CN={ENCLAVE}' and grant.findtext('default') == 'DENY'
    assert not grant.findall('deny_rule')
    rules = grant.findall('allow_rule')
    allowed = {side: {t.text for rule in rules for t in rule.findall(f'{side}/topics/topic')
                      if t.text != 'ros_discovery_info'} for side in ('publish', 'subscribe')}
    assert allowed['subscribe'] == {f'rt/{t}' for t in SUBSCRIBES} | {f'rq/ranker/{s}Request' for s in SERVES}
    assert allowed['publish'] == {f'rt/{t}' for t in PUBLISHES} | {f'rr/ranker/{s}Reply' for s in SERVES}
