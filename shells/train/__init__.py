"""The training stages: the shared loop, stage 1 (the field), stage 2 (the band), health."""
