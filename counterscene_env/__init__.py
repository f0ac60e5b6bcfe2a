"""CounterScene: an adversarial multi-agent driving environment.

A diffusion world model drives the traffic; each episode one causally selected adversary has its
safety margins removed by counterfactual guidance while everyone else reacts. See the README.
"""

__version__ = "0.1.0"
