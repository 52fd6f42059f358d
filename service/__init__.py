"""bdsfix: BeiDou receiver service with the Zhao-Cui-Lu a-priori-free fast first fix."""

__version__ = "0.1.0"
