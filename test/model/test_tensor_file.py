"""Reading a checkpoint without torch refuses what is not a weights file of its kind, each
refusal a CheckpointError that names what is wrong (the reader itself is checked against
torch.load in test/test_one_serving_model.py)."""
import zipfile

import pytest
import torch

from stars_ros.errors import CheckpointError, ConfigError
from stars_ros.model.checkpoint import read_checkpoint
from stars_ros.model.serving import encoder_serving_form
from stars_ros.model.config import ExperimentConfig
from stars_ros.model.tensor_file import read_tensor_file


def _rewritten(source, target, change):
    """``source`` (a torch.save zip) written to ``target`` with ``change(name, data)`` applied
    to each member's bytes (None: the member is left out)."""
    with zipfile.ZipFile(source) as original, zipfile.ZipFile(target, 'w') as copy:
        for name in original.namelist():
            data = change(name, original.read(name))
            if data is not None:
                copy.writestr(name, data)
    return target


def test_a_zip_without_the_pickle_or_with_a_cut_storage_is_refused_as_corrupted(tiny_checkpoint, tmp_path):
    no_pickle = _rewritten(tiny_checkpoint, tmp_path / 'no_pickle.pt',
                           lambda name, data: None if name.endswith('data.pkl') else data)
    with pytest.raises(CheckpointError, match='truncated or corrupted'):
        read_checkpoint(no_pickle)
    cut = _rewritten(tiny_checkpoint, tmp_path / 'cut.pt',
                     lambda name, data: data[:-4] if '/data/' in name and len(data) > 4 else data)
    with pytest.raises(CheckpointError, match='holds .* bytes, not .* elements'):
        read_checkpoint(cut)


def test_a_file_written_on_a_big_endian_machine_is_refused_by_name(tmp_path):
    torch.save({'weights': torch.zeros(2)}, tmp_path / 'little.pt')
    big = _rewritten(tmp_path / 'little.pt', tmp_path / 'big.pt',
                     lambda name, data: b'big' if name.endswith('/byteorder') else data)
    with pytest.raises(ValueError, match='big-endian'):
        read_tensor_file(big)


def test_a_persistent_id_other_than_a_storage_is_refused(tmp_path):
    torch.save({'weights': torch.ones(3)}, tmp_path / 'plain.pt')
    odd = _rewritten(tmp_path / 'plain.pt', tmp_path / 'odd.pt',
                     lambda name, data: data.replace(b'storage', b'storaxe') if name.endswith('data.pkl') else data)
    with pytest.raises(Exception, match="unknown persistent id 'storaxe'"):
        read_tensor_file(odd)


def test_a_config_naming_a_tabular_backbone_for_graph_scenes_is_refused():
    config = ExperimentConfig.from_dict({'encoder': {'name': 'mlp'}})
    with pytest.raises(ConfigError, match="encoder 'mlp' does not read scene graphs"):
        encoder_serving_form(config, 'graph', 7, {})


def test_the_serving_form_of_incompatible_weights_is_a_checkpoint_error(tiny_checkpoint, tmp_path):
    """Weights of another size than the config says: refused by the node's loader as by training's."""
    from stars_ros.model.checkpoint import _digest, _tensors
    from stars_ros.model.predictor import Predictor
    content = torch.load(tiny_checkpoint, weights_only=True)
    content['metadata']['config']['model']['dim'] = 32
    content['digest'] = _digest(content['metadata'], _tensors(content))
    torch.save(content, tmp_path / 'mismatch.pt')
    with pytest.raises(CheckpointError, match='incompatible with this version'):
        Predictor.load(tmp_path / 'mismatch.pt')
