"""The learners that train on their own (``registry.LEARNERS`` names their modules): each module trains an agent
(``run(cfg, agent_id)``) and rebuilds it as a policy from its checkpoint (``build_policy``). ``loop`` is the one
training loop every agent's learner runs in, and ``cloning`` behaviour cloning's fit, which the DDPGs use. A
scenario family's own learners live in its package (worldmodel/families/)."""
