"""What HIGhER adds to DQN: hindsight relabelling of failed episodes with an instruction generator.

relabel.py            the relabelling strategies (none, expert = HER, noisy expert, learned = HIGhER)
generator.py          the instruction generator (view -> instruction) and its trainer
generator_data.py     its dataset of (view, instruction) pairs from successes, and the exact-match score
generator_measure.py  the generator learning from N expert pairs, measured on seen and unseen goals
"""
