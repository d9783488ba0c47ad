"""Twin models. Every model follows the scikit-learn contract (``fit`` returns self,
fitted attributes end in ``_``) and, once fitted, opens one :class:`DayEstimator` per
operating day that is fed the day's reference readings and asked for the target."""
