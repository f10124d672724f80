"""What is learned: networks (nets/), objectives and samplers, the named models, checkpoint load/save."""
