"""Learning barriers, class-K gains and policies end to end through the safety filter.

The whole loop is differentiable: a :class:`~torchcbf.barriers.NeuralBarrier`'s Lie
derivatives (autograd with ``create_graph``), the batched QP of
:class:`~torchcbf.filters.SafetyFilter` (implicit differentiation of its KKT conditions) and
closed-loop rollouts (:func:`torchcbf.sim.simulate` with ``differentiable=True``). This
package adds the data (:mod:`~torchcbf.learning.sampling`), losses
(:mod:`~torchcbf.learning.losses`), a small smooth network (:class:`MLP`) and a training
loop with checkpoints (:func:`train`).

Example (classification plus the CBF condition at the filter's solution)::

    occ = occupancy_from_barrier(obstacles)            # or any x -> bool occupancy oracle
    train_occ = dilate(occ, 0.1)                       # a safety margin
    net = MLP(2, (64, 64), low=lo, high=hi)
    barrier = NeuralBarrier(net)
    filt = SafetyFilter(SingleIntegrator(2, u_min=-2, u_max=2), barrier, alpha=1.0)
    opt = torch.optim.Adam(barrier.parameters(), lr=3e-3)
    gen = make_generator(seed=0)

    def loss_fn(step):
        data = sample_labelled(train_occ, lo, hi, 4096, generator=gen)
        l_cls = classification_loss(barrier(data.x), data.safe, margin=0.05)
        xs = data.x[data.safe]                         # the condition holds on the safe set
        l_cbf = cbf_condition_loss(filt, xs, nominal(xs, 0.0))
        return l_cls + l_cbf, {"cls": l_cls, "cbf": l_cbf}

    train(loss_fn, opt, steps=500, checkpoint="barrier.pt", module=barrier, generator=gen)
"""

from torchcbf.learning.losses import (
    ClosedLoopLoss,
    cbf_condition_loss,
    classification_accuracy,
    classification_loss,
    closed_loop_loss,
    condition_violation,
)
from torchcbf.learning.nets import MLP
from torchcbf.learning.sampling import (
    LabelledStates,
    Occupancy,
    dilate,
    label_states,
    make_generator,
    occupancy_from_barrier,
    sample_free,
    sample_labelled,
    uniform_box,
)
from torchcbf.learning.train import TrainResult, load_checkpoint, save_checkpoint, train

__all__ = [
    "MLP",
    "ClosedLoopLoss",
    "LabelledStates",
    "Occupancy",
    "TrainResult",
    "cbf_condition_loss",
    "classification_accuracy",
    "classification_loss",
    "closed_loop_loss",
    "condition_violation",
    "dilate",
    "label_states",
    "load_checkpoint",
    "make_generator",
    "occupancy_from_barrier",
    "sample_free",
    "sample_labelled",
    "save_checkpoint",
    "train",
    "uniform_box",
]
