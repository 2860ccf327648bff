"""The verdict client: `remote.RemoteModel` asks a noisestop server over HTTP (never by
importing `service`), through the wire codec both sides share (`oip_codec`) and `token`."""
