import click
@click.command('estimate-crf')
def command():
    pass
