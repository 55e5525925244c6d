"""Chapter 4 (APEX): the policy network, its training, and the policy-guided iCEM expert (iCEM_pi).

Nothing here imports Ray or MLflow; workers/methods/apex.py runs it as a method.

Load a trained policy from a trial's artifacts (``policy/policy_NNNN.npz``)::

    from workers.policy import load_policy; pi = load_policy("policy_0007.npz"); action = pi(observation)
"""

from workers.policy.expert import ExpertSettings, ICemPi, relabel_states, run_expert_episode, run_policy_episode
from workers.policy.guidance import ACTION_NORM, GUIDANCE, AuxiliaryTerm, GuidedObjective, adaptive_lambda
from workers.policy.network import Policy, PolicyWeights, load_policy
from workers.policy.observations import ObservationReader
from workers.policy.training import PolicySettings, PolicyTrainer, TrainReport
from workers.policy.worker import RelabelWorker

__all__ = [
    "ACTION_NORM",
    "GUIDANCE",
    "AuxiliaryTerm",
    "ExpertSettings",
    "GuidedObjective",
    "ICemPi",
    "ObservationReader",
    "Policy",
    "PolicySettings",
    "PolicyTrainer",
    "PolicyWeights",
    "RelabelWorker",
    "TrainReport",
    "adaptive_lambda",
    "load_policy",
    "relabel_states",
    "run_expert_episode",
    "run_policy_episode",
]
