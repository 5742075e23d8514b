import pytest

from lerobot_murm.env import MurmEnv


@pytest.fixture
def make_env():
    """Build MurmEnvs that are closed after the test."""
    envs: list[MurmEnv] = []

    def _make(**kwargs) -> MurmEnv:
        env = MurmEnv(**kwargs)
        envs.append(env)
        return env

    yield _make
    for env in envs:
        env.close()
