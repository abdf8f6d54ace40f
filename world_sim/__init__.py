"""The world simulator. ``parallel_env`` (PettingZoo) is imported on first use only."""


def __getattr__(name: str):
    if name in ("parallel_env", "JamnavParallelEnv"):
        from world_sim import pettingzoo_env

        return getattr(pettingzoo_env, name)
    raise AttributeError(f"module 'world_sim' has no attribute {name!r}")


__all__ = ["parallel_env", "JamnavParallelEnv"]
