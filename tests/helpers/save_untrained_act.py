"""Save an untrained stock LeRobot ACT policy shaped for a `murm` env (used to drive `lerobot-eval`).

Run as a script in a fresh interpreter: the `murm` env type must come from LeRobot's own
plugin discovery, not from importing lerobot_murm first.
"""

import sys

from lerobot.configs import FeatureType
from lerobot.envs.factory import make_env_config
from lerobot.envs.utils import env_to_policy_features
from lerobot.policies.act.configuration_act import ACTConfig
from lerobot.policies.act.modeling_act import ACTPolicy
from lerobot.policies.factory import make_pre_post_processors
from lerobot.utils.import_utils import register_third_party_plugins

out_dir, task, cameras = sys.argv[1], sys.argv[2], sys.argv[3].split(",")
register_third_party_plugins()
features = env_to_policy_features(make_env_config("murm", task=task, cameras=cameras))
config = ACTConfig(
    input_features={k: v for k, v in features.items() if v.type is not FeatureType.ACTION},
    output_features={k: v for k, v in features.items() if v.type is FeatureType.ACTION},
    pretrained_backbone_weights=None,  # offline: no torchvision download
    chunk_size=100,
    n_action_steps=100,  # one forward pass per episode keeps the test fast
    dim_model=32,
    dim_feedforward=64,
    n_encoder_layers=1,
    n_decoder_layers=1,
    use_vae=False,
    device="cpu",
    push_to_hub=False,
)
preprocessor, postprocessor = make_pre_post_processors(config, dataset_stats=None)
ACTPolicy(config).save_pretrained(out_dir)
preprocessor.save_pretrained(out_dir)
postprocessor.save_pretrained(out_dir)
