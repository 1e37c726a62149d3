"""The operator's side: `hapticlink operator` feels the remote surface.

It subscribes to a session's render feed, fetches each chosen rendering model once (cached by version),
reads the operator's own device (speed and normal force), renders the texture's vibration with
`texture_library.renderer.StreamRenderer` and writes it to a sound card, a WAV file or the device.
devices: where speed and force come from; outputs: where the vibration goes; client: the loop.
"""
