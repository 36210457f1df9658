import numpy as np
import pytest
import torch

from stars_ros.model.checkpoint import FORMAT_VERSION, load_checkpoint, read_checkpoint, save_checkpoint
from stars_ros.errors import CheckpointError
from conftest import served_rows


def test_round_trip_predicts_the_same(tiny_checkpoint, synthetic, tmp_path):
    recommender, metadata = load_checkpoint(tiny_checkpoint)
    rows = np.arange(0, len(synthetic), 37)
    path = tmp_path / 'again.pt'
    save_checkpoint(recommender, path, data={'fingerprint': 'x'}, metrics={'mse': 0.1})
    again, again_metadata = load_checkpoint(path)
    assert np.array_equal(served_rows(recommender, synthetic, rows), served_rows(again, synthetic, rows))
    assert again_metadata['metrics'] == {'mse': 0.1}
    assert again.users == recommender.users and again.action_names == ('navigate',)
    assert again.rating_scale == recommender.rating_scale == (0.0, 1.0)


def test_metadata_carries_everything_needed(tiny_checkpoint, synthetic):
    metadata = read_checkpoint(tiny_checkpoint)['metadata']
    assert metadata['data']['fingerprint'] == synthetic.fingerprint
    assert metadata['config']['encoder']['name'] == 'gcn'
    assert len(metadata['normalisation']['mean']) == 1
    assert metadata['rating_scale'] == [0.0, 1.0]
    assert {'package_version', 'torch_version', 'created_utc', 'users', 'actions'} <= set(metadata)


def test_truncated_file(tiny_checkpoint, tmp_path):
    data = tiny_checkpoint.read_bytes()
    path = tmp_path / 'cut.pt'
    path.write_bytes(data[:len(data) // 2])
    with pytest.raises(CheckpointError, match='truncated or corrupted'):
        load_checkpoint(path)


def test_flipped_byte_in_weights_is_detected(tiny_checkpoint, tmp_path):
    data = bytearray(tiny_checkpoint.read_bytes())
    content = torch.load(tiny_checkpoint, weights_only=True)
    weights = content['state_dict']['encoder.project.weight'].numpy().tobytes()
    offset = bytes(data).find(weights[:64])
    assert offset > 0
    data[offset + 5] ^= 0xFF
    path = tmp_path / 'flipped.pt'
    path.write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match='corrupted'):
        load_checkpoint(path)


def test_other_version_refused(tiny_checkpoint, tmp_path):
    content = torch.load(tiny_checkpoint, weights_only=True)
    content['metadata']['format_version'] = FORMAT_VERSION + 1
    torch.save(content, tmp_path / 'future.pt')
    with pytest.raises(CheckpointError, match='format version 2 is not supported'):
        load_checkpoint(tmp_path / 'future.pt')


def test_foreign_file_refused(tmp_path):
    torch.save({'weights': torch.zeros(2)}, tmp_path / 'other.pt')
    with pytest.raises(CheckpointError, match='not a stars_ros checkpoint'):
        load_checkpoint(tmp_path / 'other.pt')
    (tmp_path / 'text.pt').write_text('hello')
    with pytest.raises(CheckpointError):
        load_checkpoint(tmp_path / 'text.pt')
    with pytest.raises(CheckpointError, match='no such checkpoint'):
        load_checkpoint(tmp_path / 'missing.pt')


class Payload:
    def __reduce__(self):
        return (print, ('code ran',))


def test_pickled_code_is_never_run(tmp_path, capsys):
    torch.save({'metadata': Payload(), 'state_dict': {}, 'digest': ''}, tmp_path / 'evil.pt')
    with pytest.raises(CheckpointError):
        load_checkpoint(tmp_path / 'evil.pt')
    assert 'code ran' not in capsys.readouterr().out


@pytest.mark.parametrize('content', [b'\x80\x02' + bytes(range(3, 256)) * 8, Payload()], ids=['garbled', 'code'])
def test_refusal_gives_no_advice_to_load_unsafely(content, tmp_path):
    """torch's own message advises weights_only=False or allow-listing globals, which would
    run the file's pickled code: that advice must not reach users of this package."""
    path = tmp_path / 'bad.pt'
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        torch.save({'metadata': content, 'state_dict': {}, 'digest': ''}, path)
    with pytest.raises(CheckpointError) as caught:
        load_checkpoint(path)
    message = str(caught.value)
    assert 'weights_only' not in message and 'safe_globals' not in message and 'trust' not in message
    assert message.startswith(f'{path}: not a')


@pytest.mark.parametrize('content, what', [(b'hello, this is text\n', 'not a torch zip/pickle file'),
                                           (b'', 'an empty file')], ids=['text', 'empty'])
def test_a_file_that_is_no_torch_file_is_named_as_such(content, what, tmp_path):
    (tmp_path / 'model.pt').write_bytes(content)
    with pytest.raises(CheckpointError) as caught:
        load_checkpoint(tmp_path / 'model.pt')
    assert str(caught.value) == f"{tmp_path / 'model.pt'}: not a stars_ros checkpoint ({what})"


def test_incompatible_weights(tiny_checkpoint, tmp_path):
    content = torch.load(tiny_checkpoint, weights_only=True)
    content['metadata']['config']['model']['dim'] = 32
    from stars_ros.model.checkpoint import _digest
    content['digest'] = _digest(content['metadata'], content['state_dict'])
    torch.save(content, tmp_path / 'mismatch.pt')
    with pytest.raises(CheckpointError, match='incompatible'):
        load_checkpoint(tmp_path / 'mismatch.pt')
