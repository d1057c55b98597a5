"""The learners that train on their own (``registry.LEARNERS`` names their modules): each module trains an agent
(``run(cfg, agent_id)``) and rebuilds it as a policy from its checkpoint (``build_policy``). A scenario family's
own learners live in its package (worldmodel/families/)."""
