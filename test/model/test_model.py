"""The StARS prediction checked by hand, and the cold-start fallback."""
import pytest
import torch

from stars_ros.model.encoders import resolve_encoder
from stars_ros.model.model import StarsModel
from stars_ros.model.vocabulary import UNKNOWN


def small_model(variant='stars'):
    model = StarsModel(resolve_encoder('mlp', 3, 2, hidden=4, layers=1), n_users=2, n_scenes=2,
                       n_actions=2, variant=variant)
    with torch.no_grad():
        if variant != 'base':
            model.user_embedding.weight.copy_(torch.tensor([[1.0, 2.0], [0.5, -1.0]]))
            model.scene_embedding.weight.copy_(torch.tensor([[0.1, 0.2], [0.0, 3.0]]))
            model.user_bias.weight.copy_(torch.tensor([[0.3], [-0.2]]))
            model.scene_bias.weight.copy_(torch.tensor([[0.05], [0.4]]))
            model.action_embedding.copy_(torch.tensor([[1.0, 0.0], [2.0, -1.0]]))
            model.bias.fill_(0.1)
    return model


def test_prediction_by_hand():
    model = small_model()
    h = torch.tensor([[0.5, 1.0]])
    # user 0: p = (1, 2); scene 1: q = (0, 3); q + h = (0.5, 4); p ⊙ (q + h) = (0.5, 8); + h = (1, 9)
    # action 0: r = (1, 0) -> 1;  action 1: r = (2, -1) -> 2 - 9 = -7
    # offsets: b_u 0.3 + b_i 0.4 + b 0.1 = 0.8
    z = model(torch.tensor([0]), torch.tensor([1]), h)
    assert z.tolist() == [pytest.approx([1.8, -6.2])]


def test_unknown_user_and_scene_use_zero_rows():
    model = small_model()
    h = torch.tensor([[0.5, 1.0]])
    # p = 0, q = 0, b_u = b_i = 0: ŷ = hᵀ r_a + b  ->  (0.5 + 0.1, 1 - 1 + 0.1)
    z = model(torch.tensor([UNKNOWN]), torch.tensor([UNKNOWN]), h)
    assert z.tolist() == [pytest.approx([0.6, 0.1])]
    # unknown scene only: p ⊙ h + h = (1, 3) for user 0 -> (1, -1) + 0.3 + 0.1
    z = model(torch.tensor([0]), torch.tensor([UNKNOWN]), h)
    assert z.tolist() == [pytest.approx([1.4, -0.6])]


def test_unknown_rows_get_no_gradient():
    model = small_model()
    z = model(torch.tensor([UNKNOWN]), torch.tensor([UNKNOWN]), torch.ones(1, 2))
    z.sum().backward()
    assert model.user_embedding.weight.grad.abs().sum() == 0
    assert model.scene_bias.weight.grad.abs().sum() == 0


def test_mf_variant_ignores_content():
    model = small_model('mf')
    assert model.encode(torch.randn(3, 3)).abs().sum() == 0
    # user 0, scene 1: p ⊙ q = (0, 6) -> action 1: -6 + 0.8
    z = model(torch.tensor([0]), torch.tensor([1]), model.encode(torch.randn(1, 3)))
    assert z[0, 1].item() == pytest.approx(-5.2)


def test_base_is_a_linear_head():
    model = small_model('base')
    h = torch.tensor([[0.5, 1.0]])
    expected = h @ model.head.weight.T + model.head.bias
    assert torch.allclose(model(torch.tensor([0]), torch.tensor([0]), h), expected)


def test_rating_scale_round_trip():
    model = small_model()
    model.target_mean.copy_(torch.tensor([3.0, 0.5]))
    model.target_std.copy_(torch.tensor([2.0, 0.1]))
    scores = torch.tensor([5.0, 0.7])
    z = model.to_z(scores, torch.tensor([0, 1]))
    assert z.tolist() == pytest.approx([1.0, 2.0])
    assert model.to_rating_scale(torch.tensor([[1.0, 2.0]])).tolist() == [pytest.approx([5.0, 0.7])]


def test_without_the_residual_h_enters_only_through_p():
    model = small_model('stars_no_residual')
    h = torch.tensor([[0.5, 1.0]])
    # user 0, scene 1: p ⊙ (q + h) = (0.5, 8), no + h; action 0: 0.5, action 1: 1 - 8; offsets 0.8
    z = model(torch.tensor([0]), torch.tensor([1]), h)
    assert z.tolist() == [pytest.approx([1.3, -6.2])]


def test_hand_over_from_the_pretrained_head_reproduces_it():
    """r_a = w_a and b = mean c_a: with p_u = 0 (its initial value with content) StARS
    scores as the head does, up to each action's intercept minus their mean."""
    model = StarsModel(resolve_encoder('mlp', 3, 2, hidden=4, layers=1), n_users=2, n_scenes=2, n_actions=2,
                       variant='stars')
    assert model.user_embedding.weight.abs().sum() == 0
    head = torch.nn.Linear(2, 2)
    h = torch.randn(4, 2)
    model.start_from_head(head)
    z = model(torch.tensor([0, 1, 0, 1]), torch.tensor([0, 0, 1, 1]), h)
    intercepts = head.bias - head.bias.mean()
    assert torch.allclose(z, head(h) - intercepts, atol=1e-6)


@pytest.mark.parametrize('variant, frozen', [('user_bias', {'user_embedding', 'scene_embedding', 'scene_bias'}),
                                             ('stars_no_q', {'scene_embedding'}), ('stars', set())])
def test_ablation_parts_are_zero_and_frozen(variant, frozen):
    model = StarsModel(resolve_encoder('mlp', 3, 2, hidden=4, layers=1), 2, 2, 2, variant=variant)
    for name in ('user_embedding', 'scene_embedding', 'user_bias', 'scene_bias'):
        weight = getattr(model, name).weight
        assert weight.requires_grad == (name not in frozen)
        if name in frozen:
            assert weight.abs().sum() == 0
    assert model.uses_content == (variant != 'user_bias')
