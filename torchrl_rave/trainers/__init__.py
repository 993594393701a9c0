"""Training helpers that plug into any TorchRL loop or ``torchrl.trainers.Trainer``."""

from torchrl_rave.trainers.curriculum import Curriculum
from torchrl_rave.trainers.seed_group import SeedGroup
from torchrl_rave.trainers.seed_streams import SeedStreams
from torchrl_rave.trainers.world_model import WorldModelTrainer

__all__ = ["Curriculum", "SeedGroup", "SeedStreams", "WorldModelTrainer"]
